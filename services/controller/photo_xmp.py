"""A drone's calibrated intrinsics and its camera's attitude from its photo's XMP (DJI's).

DJI's survey drones (Phantom 4 RTK, Mavic 3 Enterprise and Multispectral, Matrice 3D/4,
Zenmuse P1) write the lens calibration into every photo's XMP packet, as their user manuals
describe it::

    drone-dji:DewarpData="2018-03-13;fx,fy,cx,cy,k1,k2,p1,p2,k3"

- ``fx, fy``: the calibrated focal lengths in pixels of the photo as taken;
- ``cx, cy``: the principal point's offset in pixels from the photo's centre;
- ``k1, k2, p1, p2, k3``: OpenCV's distortion
  (:class:`~services.common.geometry.free_camera.LensDistortion`).

``drone-dji:DewarpFlag="1"`` says the camera has already undistorted the photo; it is then
taken to keep the calibrated camera matrix (as ``cv2.undistort`` does) with no distortion.

A photo brought down from ``W₀ × H₀`` (EXIF ``PixelXDimension`` × ``PixelYDimension``, its
original size; the photo's own when absent) to ``W × H`` scales all of these by ``s = W / W₀``:
``f = s f₀``, ``c = (W/2, H/2) + s c₀``; the distortion, on normalised coordinates, is
unchanged. A crop (another aspect than the original's) is not used, nor a calibration whose
field of view lies outside :data:`~services.controller.photo_exif.FOV_RANGE_DEG`, nor a lens that
folds the photo or has no inverse over it: such metadata is ignored, never an error.

Unlike an EXIF focal length (a nominal lens, whole millimetres), this is a measurement of the
very lens: a search uses it as intrinsics given (``source="calibration"``), which a render may
confirm. ``DewarpDataK6`` (OpenCV's rational model, k4–k6) is not read.

The same packet states the gimbal's attitude, ``drone-dji:GimbalPitchDegree`` and
``GimbalRollDegree`` (:func:`xmp_attitude`): in DJI's NED frame, rotation order ZYX, pitch −90°
looking straight down and roll about the optical axis, right side down for a positive one. In
this project's conventions (:mod:`services.common.geometry.free_camera`: pitch below the
horizontal, roll turning the camera clockwise as seen from behind it) that is pitch ``−p`` and
roll ``r``. The gimbal's yaw is a compass heading, which a scene's axes need not follow: not read.

:func:`~services.controller.photo_metadata.read_metadata` reads the packet (Pillow's
``Image.getxmp``, with ``defusedxml`` against entity expansion), without decoding pixels.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Final

from PIL import ExifTags
from pydantic import ValidationError

from services.common.contracts.free import CameraAttitude, PhotoIntrinsics
from services.common.geometry.camera import film_camera, fov_deg_of
from services.common.geometry.free_camera import LensDistortion
from services.common.geometry.lens import invertible_over_film
from services.controller.photo_exif import ASPECT_TOLERANCE, FOV_RANGE_DEG
from services.controller.photo_metadata import PhotoMetadata

__all__ = ["DEWARP_FIELDS", "xmp_attitude", "xmp_intrinsics"]

DEWARP_FIELDS: Final = 9
"""``fx, fy, cx, cy, k1, k2, p1, p2, k3`` after the calibration's date."""


def _values(xmp: object, key: str) -> Iterator[str]:
    """Every value of ``key`` in Pillow's nested XMP dictionaries (attributes and elements
    alike, by local name), depth first."""
    if isinstance(xmp, Mapping):
        for name, value in xmp.items():
            if name == key and isinstance(value, str):
                yield value
            else:
                yield from _values(value, key)
    elif isinstance(xmp, list):
        for item in xmp:
            yield from _values(item, key)


def _dewarp(text: str) -> list[float] | None:
    """The nine numbers of a ``DewarpData`` value, None unless exactly nine finite ones."""
    _, _, numbers = text.rpartition(";")
    try:
        values = [float(part) for part in numbers.split(",")]
    except ValueError:
        return None
    return values if len(values) == DEWARP_FIELDS and all(map(math.isfinite, values)) else None


def xmp_intrinsics(metadata: PhotoMetadata, size: tuple[int, int]) -> PhotoIntrinsics | None:
    """The calibrated intrinsics a photo's XMP states (``size`` = (W, H), its pixels), by the
    module docstring's rules; None when it states none usable."""
    xmp, exif = metadata.xmp, metadata.exif
    values = next((v for v in map(_dewarp, _values(xmp, "DewarpData")) if v is not None), None)
    if values is None:
        return None
    width, height = size
    original = [exif.get(ExifTags.Base.ExifImageWidth), exif.get(ExifTags.Base.ExifImageHeight)]
    try:
        w0, h0 = (float(v) for v in original)  # type: ignore[arg-type]  # ints, or absent
    except (TypeError, ValueError):
        w0, h0 = float(width), float(height)
    if not (w0 > 0 and h0 > 0) or abs(w0 / h0 / (width / height) - 1) > ASPECT_TOLERANCE:
        return None
    s = width / w0
    fx, fy, cx, cy = (s * v for v in values[:4])
    dewarped = any(v.strip() == "1" for v in _values(xmp, "DewarpFlag"))
    try:
        lens = None if dewarped else LensDistortion.of_coefficients(values[4:])
        intrinsics = PhotoIntrinsics(
            fx_px=fx,
            fy_px=fy,
            cx_px=width / 2 + cx,
            cy_px=height / 2 + cy,
            distortion=None if lens is None or lens.is_zero else lens,
            source="calibration",
        )
    except ValidationError:
        return None
    if not FOV_RANGE_DEG[0] < fov_deg_of(fx, width) < FOV_RANGE_DEG[1]:
        return None
    camera = film_camera(width, height, (fx, fy), (width / 2 + cx, height / 2 + cy))
    lens = intrinsics.distortion
    return intrinsics if lens is None or invertible_over_film(camera, lens) else None


def _angle(xmp: object, key: str) -> float | None:
    """The first value of ``key`` that reads as a finite number of degrees, else None."""
    for text in _values(xmp, key):
        try:
            value = float(text)
        except ValueError:
            continue
        if math.isfinite(value):
            return value
    return None


def xmp_attitude(metadata: PhotoMetadata) -> CameraAttitude | None:
    """The camera's pitch and roll that a photo's XMP states through its gimbal's angles
    (module docstring), None when it states no usable pair."""
    xmp = metadata.xmp
    pitch, roll = _angle(xmp, "GimbalPitchDegree"), _angle(xmp, "GimbalRollDegree")
    if pitch is None or roll is None:
        return None
    try:
        return CameraAttitude(pitch_deg=-pitch, roll_deg=roll)
    except ValidationError:
        return None
