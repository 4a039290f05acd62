"""Safe decoding of uploaded images (every service): PNG, JPEG or binary PPM, sized from the header.

The header is read here, in Python, so an image whose width x height exceeds the cap is refused
before OpenCV allocates anything (a small PNG can declare 60000 x 60000 pixels of zeros: a
decompression bomb), and so a service can budget the memory a decode will take
(:attr:`ImageHeader.decoded_bytes`) before it starts. Only the PNG and JPEG decoders are
reachable; other formats OpenCV knows (TIFF, WebP, JPEG 2000, ...) are refused by their
signature. A JPEG whose scans stop short is refused too, though OpenCV would decode it. Binary
PPM (``P6``, 8-bit) is read here without a codec: the uncompressed format the renderer hands to
the detector.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal

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
    "jpeg_reduction",
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
_JPEG_SEQUENTIAL = frozenset({0xC0, 0xC1, 0xC9})  # their scans code every coefficient at once
_JPEG_LOSSLESS = frozenset({0xC3, 0xC7, 0xCB, 0xCF})  # no coefficients at all
_JPEG_NEXT_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
"""The first marker after a scan's data: there 0xFF 0x00 is a stuffed 0xFF, RSTn restarts."""
PPM_MEDIA_TYPE = "image/x-portable-pixmap"
_PPM_MAGIC = b"P6"
_PPM_MAX_HEADER = 1024  # magic, three numbers, comments: a real header has a few dozen bytes
_PPM_FIELD = rb"(?:(?:\s|#[^\n]*\n)+(\d{1,9}))"  # whitespace or comment lines, then a number
_PPM_HEADER = re.compile(_PPM_MAGIC + _PPM_FIELD * 3 + rb"\s")
_READ_RGB: int = getattr(cv2, "IMREAD_COLOR_RGB", cv2.IMREAD_COLOR)
"""Decode straight to RGB (OpenCV >= 4.11): no second array for a BGR-to-RGB copy."""
_REDUCED_BGR = {
    2: cv2.IMREAD_REDUCED_COLOR_2,
    4: cv2.IMREAD_REDUCED_COLOR_4,
    8: cv2.IMREAD_REDUCED_COLOR_8,
}
"""libjpeg's scaled decodes (to BGR) by their factor."""
_JPEG_CORNER = 4  # pixels of the bottom-right corner compared with libjpeg's grey fill
_JPEG_PROBE = bytes(np.random.default_rng(15).integers(0, 0xFF, 512, dtype=np.uint8))
"""Fixed bytes, none 0xFF (so never a marker), that decode as entropy-coded data."""


_PNG_CHANNELS = {
    0: 1,
    2: 3,
    3: 1,
    4: 2,
    6: 4,
}  # by colour type: grey, RGB, palette, grey+alpha, RGBA
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
DECODED_CHANNELS = 3
"""Every image decodes to 8-bit RGB."""


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header says: its format, size in pixels and samples per pixel."""

    format: ImageFormat
    width: int
    height: int
    offset: int = 0
    """Where the pixel data starts (PPM only)."""
    channels: int = 3
    """Samples per pixel as stored (a palette PNG stores one, an index)."""
    bit_depth: int = 8
    """Bits per sample as stored."""

    @property
    def decoded_bytes(self) -> int:
        """Bytes a decode of this image holds at once: the larger of its samples as stored,
        ``width x height x channels x bit_depth / 8``, and the 8-bit RGB array it becomes,
        ``width x height x 3``.

        OpenCV decodes a PNG or JPEG row by row into the RGB array (a 4096 x 4096 16-bit RGBA
        PNG took 51 MB, the array's size, not the 134 MB of its samples); the larger figure is
        kept so that a decoder which expands the stored samples first is still covered.
        """
        stored = -(-self.width * self.height * self.channels * self.bit_depth // 8)
        return max(stored, self.width * self.height * DECODED_CHANNELS)


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
    # The IHDR chunk must come first: length 13, then width and height as big-endian uint32,
    # then bit depth and colour type.
    if len(data) < 33 or data[12:16] != b"IHDR" or int.from_bytes(data[8:12], "big") != 13:
        raise _invalid("the PNG has no valid IHDR header (truncated or corrupt)")
    width = int.from_bytes(data[16:20], "big")
    height = int.from_bytes(data[20:24], "big")
    if width == 0 or height == 0:
        raise _invalid(f"the PNG declares a size of {width}x{height} pixels")
    depth, colour_type = data[24], data[25]
    if depth not in _PNG_DEPTHS.get(colour_type, ()):
        raise _invalid(f"the PNG declares colour type {colour_type} at bit depth {depth}")
    return ImageHeader("png", width, height, channels=_PNG_CHANNELS[colour_type], bit_depth=depth)


def _jpeg_header(data: bytes) -> ImageHeader:
    """Walk the marker segments up to the start of scan; the frame header has the size."""
    frame: tuple[int, int, int, int] | None = None  # width, height, components, precision
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
            precision = data[pos + 2]
            height = int.from_bytes(data[pos + 3 : pos + 5], "big")
            width = int.from_bytes(data[pos + 5 : pos + 7], "big")
            frame = (width, height, data[pos + 7], precision)
        if marker == _JPEG_SOS:
            if frame is None:
                raise _invalid("the JPEG has no frame header before its image data")
            # A complete file ends with EOI (possibly followed by padding).
            if data.rfind(b"\xff\xd9", pos + length) < 0:
                raise _invalid("the JPEG is truncated (no end-of-image marker)")
            width, height, components, precision = frame
            if width == 0 or height == 0:
                raise _invalid(f"the JPEG declares a size of {width}x{height} pixels")
            if not 1 <= components <= 4 or not 2 <= precision <= 16:
                raise _invalid(f"the JPEG declares {components} components of {precision} bits")
            return ImageHeader("jpeg", width, height, channels=components, bit_depth=precision)
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


def decode_image(
    data: bytes, *, max_pixels: int, max_side: int, at_least: tuple[int, int] | None = None
) -> NDArray[np.uint8]:
    """Decode PNG, JPEG or binary PPM bytes to an 8-bit RGB ``(H, W, 3)`` array.

    Grey, palette, 16-bit and alpha images are converted to 8-bit RGB (alpha dropped). EXIF
    orientation is ignored: the array is the stored pixel grid, whose size the header states.

    With ``at_least`` ``(w, h)``, for a caller that shrinks the image to about that size anyway,
    a JPEG is decoded already shrunk by libjpeg's scaled IDCT, by the largest of 2, 4 and 8
    (:func:`jpeg_reduction`) that keeps it at least that large: the array is then ``H / f x
    W / f``. A 4000 x 3000 JPEG decoded in 17 ms at an eighth, 93 ms whole.

    Raises
    ------
    PayloadTooLargeError, UnprocessableError, UnsupportedMediaTypeError
        As :func:`checked_header`; also (422) when the image data cannot be decoded.
    """
    header = checked_header(data, max_pixels=max_pixels, max_side=max_side)
    if header.format == "ppm":
        return _decode_ppm(data, header)
    factor = jpeg_reduction(header, at_least)
    flags = (_READ_RGB if factor == 1 else _REDUCED_BGR[factor]) | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        decoded = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as exc:  # OpenCV's own size cap, or a decoder that throws
        raise _invalid(f"the {header.format.upper()} image could not be decoded") from exc
    if decoded is None:
        raise _invalid(f"the {header.format.upper()} image is truncated or corrupt")
    size = (-(-header.height // factor), -(-header.width // factor))
    if decoded.shape[:2] != size or decoded.ndim != 3:
        raise _invalid("the decoded image does not match the size its header declares")
    if header.format == "jpeg" and not _jpeg_scans_complete(data):
        raise _invalid("the JPEG's scans end before every coefficient is coded (truncated)")
    if header.format == "jpeg" and not _jpeg_tail_decoded(data, decoded):
        raise _invalid("the JPEG's image data ends before its last block (truncated)")
    if factor > 1 or _READ_RGB == cv2.IMREAD_COLOR:  # decoded to BGR
        decoded = cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    return np.asarray(decoded, dtype=np.uint8)


def jpeg_reduction(header: ImageHeader, at_least: tuple[int, int] | None) -> int:
    """How many times :func:`decode_image` shrinks the image of ``header`` as it decodes it to
    keep it at least ``at_least`` ``(w, h)``: 2, 4 or 8 for a JPEG that large whose sides it
    divides (a partial last pixel would stretch the image when it is resized), else 1. Cameras'
    sizes are multiples of 8 (4000 x 3000, 5472 x 3648, 3840 x 2160)."""
    if header.format != "jpeg" or at_least is None:
        return 1
    w, h = header.width, header.height
    fits = [f for f in _REDUCED_BGR if w % f == 0 and h % f == 0]  # no partial pixel at an edge
    return max((f for f in fits if w // f >= at_least[0] and h // f >= at_least[1]), default=1)


def _jpeg_scans_complete(data: bytes) -> bool:
    """Whether the JPEG's scans, as their headers state, code every coefficient of every
    component to full precision.

    A progressive JPEG codes its coefficients over several scans, each naming its components,
    its band of coefficients (``Ss`` to ``Se``) and the bit it ends at (``Al``); a file cut
    short, even with an end marker appended, lacks the later scans. So do the later components'
    scans of a sequential JPEG that codes them one scan each. The markers are walked from the
    start, skipping each scan's entropy-coded data; lossless JPEG has no coefficients and passes.
    """
    coded: dict[int, list[int | None]] = {}  # component id -> per coefficient, the last Al
    sequential = True
    pos, end = 2, len(data)
    for _ in range(_JPEG_MAX_SEGMENTS):
        while pos < end and data[pos] == 0xFF:
            pos += 1
        if pos >= end:
            return False
        marker = data[pos]
        pos += 1
        if marker == _JPEG_EOI:
            break
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:
            continue
        length = int.from_bytes(data[pos : pos + 2], "big")
        if length < 2 or pos + length > end:
            return False
        segment = data[pos + 2 : pos + length]
        pos += length
        if marker in _JPEG_LOSSLESS:
            return True
        if marker in _JPEG_SOF and len(segment) >= 6:
            sequential = marker in _JPEG_SEQUENTIAL
            ids = segment[6 : 6 + 3 * segment[5] : 3]
            coded = {component: [None] * 64 for component in ids}
        elif marker == _JPEG_SOS and segment:
            count = segment[0]
            if len(segment) < 4 + 2 * count:
                return False
            ss, se, al = segment[1 + 2 * count], segment[2 + 2 * count], segment[3 + 2 * count] & 15
            band = range(64) if sequential else range(ss, min(se, 63) + 1)
            for component in segment[1 : 1 + 2 * count : 2]:
                if component not in coded:
                    return False
                for k in band:
                    coded[component][k] = 0 if sequential else al
            found = _JPEG_NEXT_MARKER.search(data, pos)
            if found is None:
                return False
            pos = found.start()
    return bool(coded) and all(al == 0 for bands in coded.values() for al in bands)


def _jpeg_tail_decoded(data: bytes, decoded: NDArray[Any]) -> bool:
    """Whether the JPEG's entropy-coded data lasted to its last blocks.

    libjpeg, inside OpenCV, decodes a scan that stops early (a truncated file with an end
    marker appended) without an error: it prints a warning to stderr and leaves the missing
    blocks at zero, which is the uniform grey 128. So a decoded image whose last pixels are not
    exactly that grey had data to its end. One that is may really end in grey; then the file is
    decoded twice more, in grey at half its width and height: as it is, and with
    :data:`_JPEG_PROBE` (bytes that decode as entropy-coded data, never as a marker) put before
    its end marker. A complete scan ignores those bytes (it ends after its last block); an
    incomplete one decodes them into its missing blocks, and the image changes. (A complete file
    that ends in grey makes libjpeg print one "extraneous bytes" warning then.)

    A progressive JPEG cut inside a later refinement scan keeps the coarser blocks of the scans
    before it and is decoded at that precision, as progressive JPEG is meant to degrade; one cut
    inside its first scan ends in grey and is refused.
    """
    corner = decoded[-_JPEG_CORNER:, -_JPEG_CORNER:]
    if not bool((corner == 128).all()):
        return True
    end = data.rfind(b"\xff\xd9")
    probed = data[:end] + _JPEG_PROBE + data[end:]
    quarter = cv2.IMREAD_REDUCED_GRAYSCALE_2 | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        plain = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), quarter)
        probe = cv2.imdecode(np.frombuffer(probed, dtype=np.uint8), quarter)
    except cv2.error:
        return False
    return plain is not None and probe is not None and np.array_equal(plain, probe)
