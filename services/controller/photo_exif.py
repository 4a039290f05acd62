"""A photo's focal length from its EXIF: what a camera or drone wrote when it took the photo.

A free search that was given no intrinsics takes them from here, so that a photo straight off a
camera is solved as one whose field of view is known (3 objects suffice; no focal length to
trade against distance). Two ways, in this order:

1. ``FocalLengthIn35mmFilm`` ``f35`` (mm): the lens a full-frame camera (36 × 24 mm, diagonal
   ``D35 = √(36² + 24²) ≈ 43.27`` mm) would need for the same angle of view over the diagonal,
   as CIPA DC-008 defines it. It survives resizing: ``f_px = f35 · √(W² + H²) / D35``.
2. ``FocalLength`` ``f`` (mm) with ``FocalPlaneXResolution`` ``r`` pixels per
   ``FocalPlaneResolutionUnit`` ``u`` (inch, cm, mm or µm, in mm): ``f_px = f · r / u`` on the
   sensor's full width, ``PixelXDimension`` pixels when stated, scaled by ``W`` over it.

Neither holds for a crop: when ``PixelXDimension`` × ``PixelYDimension`` has another aspect than
the image (by more than :data:`ASPECT_TOLERANCE`), the EXIF is not used. A focal length whose
horizontal field of view falls outside :data:`FOV_RANGE_DEG` is not used either. Unreadable or
missing EXIF is not an error: the search estimates the focal length from the boxes instead.

A focal length found is used as if given, in the box solve and in the dense refinement.
``FocalLengthIn35mmFilm`` is a whole number of millimetres, so it is up to ~2 % off at 24 mm;
fitting the focal length densely from it did worse all the same (9 views of demo, once each
way: two of 9 then 5.2 % and 6.9 % of the radius off, none so with it kept). ``python -m
benchmarks.exif_focal`` (16 drone views of demo and garden, 640 × 480 JPEGs) measured once:
with the EXIF read, 100 % within 2 % of the radius and 1°, median 0.72 %; with it not read,
56 %, median 1.48 %; with the fov given exactly, 100 %, median 0.35 %. No answer is confirmed
on an EXIF focal length (:mod:`~services.controller.free_loop`): with one 15 % too long, the
answers were 14 % off, and their renders agreed all the same. The render's edges overrule one
that they clearly put elsewhere (:mod:`~services.controller.exif_check`).

Only a JPEG's EXIF is read (what cameras and drones write), by
:func:`~services.controller.photo_metadata.read_metadata`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from PIL import ExifTags

from services.common.contracts.free import PhotoIntrinsics
from services.common.geometry.camera import fov_deg_of
from services.controller.photo_metadata import PhotoMetadata

__all__ = ["ASPECT_TOLERANCE", "FOV_RANGE_DEG", "ExifFocal", "exif_focal", "exif_intrinsics"]

FULL_FRAME_DIAGONAL_MM: Final = math.hypot(36.0, 24.0)
ASPECT_TOLERANCE: Final = 0.01
"""Relative difference of width/height between the image and the EXIF's pixel dimensions above
which the image is taken for a crop (a resize keeps the aspect to within a pixel)."""
FOV_RANGE_DEG: Final = (1.0, 170.0)
UNIT_MM: Final = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
"""FocalPlaneResolutionUnit: inch, centimetre, and the millimetre and micrometre of Exif 3."""


@dataclass(frozen=True)
class ExifFocal:
    """The focal length in the image's pixels (square pixels, centred principal point) and the
    EXIF tag it came from, in words."""

    focal_px: float
    tag: str


def _number(value: object) -> float | None:
    try:
        number = float(value)  # type: ignore[arg-type]  # IFDRational, int or float
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0.0 else None


def exif_focal(metadata: PhotoMetadata, size: tuple[int, int]) -> ExifFocal | None:
    """The focal length a photo's EXIF states (``size`` = (W, H), its pixels), by the module
    docstring's rules; None when it states none that can be used."""
    tags = metadata.exif
    width, height = size
    sensor_w = _number(tags.get(ExifTags.Base.ExifImageWidth))
    sensor_h = _number(tags.get(ExifTags.Base.ExifImageHeight))
    if sensor_w and sensor_h and abs(sensor_w / sensor_h / (width / height) - 1) > ASPECT_TOLERANCE:
        return None
    found: ExifFocal | None = None
    f35 = _number(tags.get(ExifTags.Base.FocalLengthIn35mmFilm))
    if f35 is not None:
        found = ExifFocal(
            f35 * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM,
            f"FocalLengthIn35mmFilm {f35:g} mm",
        )
    else:
        focal = _number(tags.get(ExifTags.Base.FocalLength))
        per_unit = _number(tags.get(ExifTags.Base.FocalPlaneXResolution))
        unit = UNIT_MM.get(int(_number(tags.get(ExifTags.Base.FocalPlaneResolutionUnit)) or 2))
        if focal is not None and per_unit is not None and unit is not None:
            full_width = (sensor_w or width) / width
            found = ExifFocal(
                focal * per_unit / unit / full_width,
                f"FocalLength {focal:g} mm at FocalPlaneXResolution {per_unit:g}",
            )
    if found is None:
        return None
    fov = fov_deg_of(found.focal_px, width)
    return found if FOV_RANGE_DEG[0] < fov < FOV_RANGE_DEG[1] else None


def exif_intrinsics(metadata: PhotoMetadata, size: tuple[int, int]) -> PhotoIntrinsics | None:
    """:func:`exif_focal` as the photo's intrinsics (``source="exif"``), None without one."""
    found = exif_focal(metadata, size)
    if found is None:
        return None
    return PhotoIntrinsics(fx_px=found.focal_px, fy_px=found.focal_px, source="exif")
