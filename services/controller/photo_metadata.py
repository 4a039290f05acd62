"""What a photo says of itself, read once: its EXIF sub-IFD and its XMP packet.

:mod:`~services.controller.photo_exif` (a focal length) and :mod:`~services.controller.photo_xmp`
(a drone's calibration and gimbal angles) interpret what this reads. Pillow parses both from the
JPEG's APP1 segments without decoding pixels (``Image.open`` is lazy; ``getxmp`` goes through
``defusedxml``, which refuses entity declarations). Only a JPEG is read: a PNG's ``eXIf`` chunk
may follow the pixels, which Pillow would then decode. Each part that cannot be read is empty,
the other kept: metadata never fails a search.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

from PIL import ExifTags, Image

__all__ = ["PhotoMetadata", "read_metadata"]


@dataclass(frozen=True)
class PhotoMetadata:
    """A photo's EXIF sub-IFD (tag number → value) and XMP packet (Pillow's nested dictionaries,
    by local name); empty when absent or unreadable."""

    exif: Mapping[int, object] = field(default_factory=dict)
    xmp: Mapping[str, object] = field(default_factory=dict)


def read_metadata(image: bytes) -> PhotoMetadata:
    """The metadata of ``image`` (an encoded image's bytes); none unless it is a JPEG."""
    if not image.startswith(b"\xff\xd8"):
        return PhotoMetadata()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Pillow's decompression-bomb warning: no pixels read
        try:
            opened = Image.open(io.BytesIO(image))
        except Exception:  # noqa: BLE001 - an unreadable photo has no metadata, never a failure
            return PhotoMetadata()
        with opened:
            try:
                exif: Mapping[int, object] = dict(opened.getexif().get_ifd(ExifTags.IFD.Exif))
            except Exception:  # noqa: BLE001 - a broken EXIF reads as none
                exif = {}
            try:
                xmp: Mapping[str, object] = opened.getxmp()
            except Exception:  # noqa: BLE001 - a broken or hostile XMP packet reads as none
                xmp = {}
    return PhotoMetadata(exif, xmp)
