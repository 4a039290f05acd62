"""Safe decoding of uploaded images (every service): PNG, JPEG or binary PPM, sized from the header.

The header is read here, in Python, so an image whose width x height exceeds the cap is refused
before OpenCV allocates anything (a small PNG can declare 60000 x 60000 pixels of zeros: a
decompression bomb). Only the PNG and JPEG decoders are reachable; other formats OpenCV knows
(TIFF, WebP, JPEG 2000, ...) are refused by their signature. Binary PPM (``P6``, 8-bit) is read
here without a codec: it is the uncompressed format the renderer hands to the detector.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.errors import (
    PayloadTooLargeError,
    UnprocessableError,
    UnsupportedMediaTypeError,
)

__all__ = [
    "PPM_MEDIA_TYPE",
    "ImageHeader",
    "checked_header",
    "decode_image",
    "encode_ppm",
    "media_type_of",
    "read_header",
]

ImageFormat = Literal["png", "jpeg", "ppm"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"
# Start-of-frame markers carry the size: SOF0-3, 5-7, 9-11, 13-15 (C4, C8 and CC are not frames).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_SOS, _JPEG_EOI = 0xDA, 0xD9
_JPEG_MAX_SEGMENTS = 4096  # a real header has a few dozen; this bounds the scan of a hostile one
PPM_MEDIA_TYPE = "image/x-portable-pixmap"
_PPM_MAGIC = b"P6"
_PPM_MAX_HEADER = 1024  # magic, three numbers, comments: a real header has a few dozen bytes
_PPM_FIELD = rb"(?:(?:\s|#[^\n]*\n)+(\d{1,9}))"  # whitespace or comment lines, then a number
_PPM_HEADER = re.compile(_PPM_MAGIC + _PPM_FIELD * 3 + rb"\s")


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header says: its format and size in pixels."""

    format: ImageFormat
    width: int
    height: int
    offset: int = 0
    """Where the pixel data starts (PPM only)."""


def media_type_of(data: bytes) -> str:
    """The media type of PNG, JPEG or binary PPM bytes, by signature."""
    if data.startswith(_PNG_SIGNATURE):
        return "image/png"
    if data.startswith(_JPEG_SOI):
        return "image/jpeg"
    if data.startswith(_PPM_MAGIC):
        return PPM_MEDIA_TYPE
    return "application/octet-stream"


def _invalid(detail: str) -> UnprocessableError:
    return UnprocessableError(detail, field="image", slug="invalid-image", title="Invalid image")


def read_header(data: bytes) -> ImageHeader:
    """The format and size of a PNG, JPEG or binary PPM image, read from its first bytes.

    Raises
    ------
    UnprocessableError
        Empty data, or an image whose header is malformed, truncated or declares no pixels.
    UnsupportedMediaTypeError
        Anything that is neither PNG, JPEG nor binary PPM.
    """
    if not data:
        raise UnprocessableError(
            "the uploaded image is empty", field="image", slug="empty-image", title="Empty image"
        )
    if data.startswith(_PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(_JPEG_SOI):
        return _jpeg_header(data)
    if data.startswith(_PPM_MAGIC):
        return _ppm_header(data)
    raise UnsupportedMediaTypeError(
        "the upload is not a PNG, JPEG or binary PPM image (by its signature)",
        field="image",
        slug="unsupported-image-format",
        title="Unsupported image format",
    )


def _png_header(data: bytes) -> ImageHeader:
    # The IHDR chunk must come first: length 13, then width and height as big-endian uint32.
    if len(data) < 33 or data[12:16] != b"IHDR" or int.from_bytes(data[8:12], "big") != 13:
        raise _invalid("the PNG has no valid IHDR header (truncated or corrupt)")
    width = int.from_bytes(data[16:20], "big")
    height = int.from_bytes(data[20:24], "big")
    if width == 0 or height == 0:
        raise _invalid(f"the PNG declares a size of {width}x{height} pixels")
    return ImageHeader("png", width, height)


def _jpeg_header(data: bytes) -> ImageHeader:
    """Walk the marker segments up to the start of scan; the frame header has the size."""
    size: tuple[int, int] | None = None
    pos, end = 2, len(data)
    for _ in range(_JPEG_MAX_SEGMENTS):
        if pos >= end or data[pos] != 0xFF:
            raise _invalid("the JPEG header is truncated or corrupt")
        while pos < end and data[pos] == 0xFF:  # fill bytes may pad any marker
            pos += 1
        if pos >= end:
            raise _invalid("the JPEG header is truncated")
        marker = data[pos]
        pos += 1
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # markers without a length
            continue
        if marker in (0xD8, _JPEG_EOI):
            raise _invalid("the JPEG ends or restarts before its image data")
        if pos + 2 > end:
            raise _invalid("the JPEG header is truncated")
        length = int.from_bytes(data[pos : pos + 2], "big")
        if length < 2 or pos + length > end:
            raise _invalid("the JPEG header is truncated or corrupt")
        if marker in _JPEG_SOF:
            if length < 8:
                raise _invalid("the JPEG frame header is corrupt")
            height = int.from_bytes(data[pos + 3 : pos + 5], "big")
            width = int.from_bytes(data[pos + 5 : pos + 7], "big")
            size = (width, height)
        if marker == _JPEG_SOS:
            if size is None:
                raise _invalid("the JPEG has no frame header before its image data")
            # A complete file ends with EOI (possibly followed by padding).
            if data.rfind(b"\xff\xd9", pos + length) < 0:
                raise _invalid("the JPEG is truncated (no end-of-image marker)")
            width, height = size
            if width == 0 or height == 0:
                raise _invalid(f"the JPEG declares a size of {width}x{height} pixels")
            return ImageHeader("jpeg", width, height)
        pos += length
    raise _invalid("the JPEG header has too many segments")


def _ppm_header(data: bytes) -> ImageHeader:
    """``P6``, then width, height and maxval as decimal numbers, each after whitespace or
    ``#`` comments, then exactly one whitespace byte and the pixels."""
    match = _PPM_HEADER.match(data[:_PPM_MAX_HEADER])
    if match is None:
        raise _invalid("the PPM header is truncated or corrupt")
    width, height, maxval = (int(group) for group in match.groups())
    if maxval != 255:
        raise UnsupportedMediaTypeError(
            f"only 8-bit PPM images (maxval 255) are accepted, not maxval {maxval}",
            field="image",
            slug="unsupported-image-format",
            title="Unsupported image format",
        )
    if width == 0 or height == 0:
        raise _invalid(f"the PPM declares a size of {width}x{height} pixels")
    return ImageHeader("ppm", width, height, offset=match.end())


def encode_ppm(rgb: NDArray[np.uint8]) -> bytes:
    """Binary PPM (``P6``, 8-bit) bytes of an RGB ``(H, W, 3)`` image: no compression at all."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb.shape} {rgb.dtype}")
    height, width = rgb.shape[:2]
    return b"P6\n%d %d\n255\n" % (width, height) + np.ascontiguousarray(rgb).tobytes()


def _decode_ppm(data: bytes, header: ImageHeader) -> NDArray[np.uint8]:
    size = header.width * header.height * 3
    if len(data) - header.offset < size:
        raise _invalid("the PPM image is truncated")
    pixels = np.frombuffer(data, dtype=np.uint8, count=size, offset=header.offset)
    return pixels.reshape(header.height, header.width, 3).copy()


def checked_header(data: bytes, *, max_pixels: int, max_side: int) -> ImageHeader:
    """:func:`read_header`, and the caps on the size it declares (no pixel is decoded).

    Raises
    ------
    PayloadTooLargeError
        The header declares more than ``max_pixels`` pixels or a side over ``max_side``.
    UnprocessableError, UnsupportedMediaTypeError
        As :func:`read_header`.
    """
    header = read_header(data)
    pixels = header.width * header.height
    if pixels > max_pixels or max(header.width, header.height) > max_side:
        raise PayloadTooLargeError(
            f"the image is {header.width}x{header.height} pixels; the limit is {max_pixels} "
            f"pixels and {max_side} per side",
            field="image",
            slug="image-too-large",
            title="Image too large",
        )
    return header


def decode_image(data: bytes, *, max_pixels: int, max_side: int) -> NDArray[np.uint8]:
    """Decode PNG, JPEG or binary PPM bytes to an 8-bit RGB ``(H, W, 3)`` array.

    Grey, palette, 16-bit and alpha images are converted to 8-bit RGB (alpha dropped). EXIF
    orientation is ignored: the array is the stored pixel grid, whose size the header states.

    Raises
    ------
    PayloadTooLargeError, UnprocessableError, UnsupportedMediaTypeError
        As :func:`checked_header`; also (422) when the image data cannot be decoded.
    """
    header = checked_header(data, max_pixels=max_pixels, max_side=max_side)
    if header.format == "ppm":
        return _decode_ppm(data, header)
    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as exc:  # OpenCV's own size cap, or a decoder that throws
        raise _invalid(f"the {header.format.upper()} image could not be decoded") from exc
    if bgr is None:
        raise _invalid(f"the {header.format.upper()} image is truncated or corrupt")
    if bgr.shape[:2] != (header.height, header.width) or bgr.ndim != 3:
        raise _invalid("the decoded image does not match the size its header declares")
    return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)
