"""A free camera resolved for rendering: the camera of the image and the pinhole Mitsuba renders.

Mitsuba's ``perspective`` sensor is a pinhole with square pixels, a horizontal fov and a
principal-point offset. A camera it can be (no distortion, ``fx = fy``) is rendered directly. Any
other (distortion, or ``fx ≠ fy``) is rendered through a *rendered* pinhole at the same pose with
square pixels of focal length ``f = max(fx, fy)`` (so no direction is sampled more coarsely than
in the image) on a film just large enough to hold every pixel's undistorted ray, then resampled
into the image with ``cv2.remap``: each image pixel centre (u, v) is undistorted
(:func:`~services.common.geometry.lens.undistort_pixels`) to normalised (x, y), which the rendered
pinhole sees at ``(f x + c'x, f y + c'y)``. Colour is interpolated bilinearly; object ids and
masks take the nearest rendered pixel, so the ground-truth boxes are those of the warped image.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from cachetools import LRUCache, cached
from numpy.typing import NDArray

from services.common.geometry.camera import PinholeCamera, fov_deg_of
from services.common.geometry.free_camera import LensDistortion
from services.common.geometry.lens import undistort_pixels

__all__ = ["FILM_STEP_PX", "FreeView", "plan_free_view"]

_MARGIN_PX = 2  # rendered pixels kept beyond the outermost ray, for bilinear interpolation
FILM_STEP_PX = 64
"""A warped view's rendered film (distortion, or ``fx ≠ fy``) is padded evenly to a multiple of
this many pixels each way (whole pixels, so every ray keeps its place in the pixel grid). The
engine loads the scene, and records its frozen render, once per film size (~0.3 s), and every
lens has an extent of its own: a free search that estimates the photo's lens renders through a
new one each time. ``python -m benchmarks.lens_films`` (demo, 320 x 240 through 10 lenses,
``k1`` −0.05…−0.15, twice over, one run): 10 film sizes → 2, median 393 → 160 ms a render."""
_MAX_EXTENT_PX = 1e7  # far beyond any film cap, still exact as int and float32


@dataclass(frozen=True, eq=False)
class FreeView:
    """What a free camera's image is (``camera``, ``distortion``) and how it is made: Mitsuba
    renders ``rendered``; when ``map_x``/``map_y`` are set, :meth:`warp` resamples that into the
    image (``cv2.remap`` maps: the rendered pixel, centre-based, of each image pixel)."""

    camera: PinholeCamera
    distortion: LensDistortion | None
    rendered: PinholeCamera
    map_x: NDArray[np.float32] | None = None
    map_y: NDArray[np.float32] | None = None

    def warp(self, image: NDArray[np.float32], *, nearest: bool = False) -> NDArray[np.float32]:
        """``image`` (rendered film, ``(h, w)`` or ``(h, w, c)`` float32) as the camera's image;
        ``nearest`` for ids and masks. Unchanged when the camera is rendered directly."""
        if self.map_x is None or self.map_y is None:
            return image
        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        warped = cv2.remap(
            image, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_REPLICATE
        )
        return np.asarray(warped, dtype=np.float32)


def _rendered_pinhole(
    camera: PinholeCamera, focal: float, width: int, height: int, cx: float, cy: float
) -> PinholeCamera:
    return camera.model_copy(
        update={
            "width": width,
            "height": height,
            "fov_deg": fov_deg_of(focal, width),
            "fx": focal,
            "fy": focal,
            "cx": cx,
            "cy": cy,
        }
    )


@dataclass(frozen=True, eq=False)
class _Warp:
    """The rendered pinhole's film and intrinsics, and the maps into the image's film."""

    width: int
    height: int
    focal: float
    cx: float
    cy: float
    map_x: NDArray[np.float32]
    map_y: NDArray[np.float32]


# The maps depend on the intrinsics and the lens only, never on the pose: a search renders many
# poses through one photo's lens, and undistorting every pixel costs ~0.3 s at 640x480 (~1 µs a
# pixel), so the last few lenses are kept (up to ~5 MB each at 640x480).
_WARPS: LRUCache[tuple[object, ...], _Warp] = LRUCache(maxsize=8)


def _lens_key(camera: PinholeCamera, lens: LensDistortion | None) -> tuple[object, ...]:
    return (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, lens)


@cached(_WARPS, key=_lens_key, lock=threading.Lock())
def _warp(camera: PinholeCamera, lens: LensDistortion | None) -> _Warp:
    """The warp of ``camera``'s image from its rendered pinhole (module docstring); only the
    intrinsics and the lens matter. Raises ``ValueError`` when the lens cannot be inverted over
    the film."""
    us, vs = np.meshgrid(
        np.arange(camera.width, dtype=np.float64) + 0.5,
        np.arange(camera.height, dtype=np.float64) + 0.5,
    )
    xy: NDArray[np.float64]
    if lens is None:
        xy = np.stack([(us - camera.cx) / camera.fx, (vs - camera.cy) / camera.fy], axis=-1)
    else:
        xy = undistort_pixels(np.stack([us, vs], axis=-1), camera, lens)
    focal = max(camera.fx, camera.fy)
    scaled = xy * focal
    if not np.isfinite(scaled).all() or np.abs(scaled).max() > _MAX_EXTENT_PX:
        raise ValueError("the lens spreads the film's rays beyond any renderable film")
    lo = np.floor(scaled.min(axis=(0, 1))) - _MARGIN_PX
    hi = np.ceil(scaled.max(axis=(0, 1))) + _MARGIN_PX
    pad = -(hi - lo) % FILM_STEP_PX  # padded evenly to the next film size of the step
    if pad.any():
        lo -= pad // 2
        hi += pad - pad // 2
    cx, cy = float(-lo[0]), float(-lo[1])
    map_x = (scaled[..., 0] + cx - 0.5).astype(np.float32)
    map_y = (scaled[..., 1] + cy - 0.5).astype(np.float32)
    map_x.setflags(write=False)  # shared by every view through this lens
    map_y.setflags(write=False)
    return _Warp(int(hi[0] - lo[0]), int(hi[1] - lo[1]), focal, cx, cy, map_x, map_y)


def plan_free_view(camera: PinholeCamera, distortion: LensDistortion | None) -> FreeView:
    """How to render ``camera`` with ``distortion`` (module docstring).

    Raises ``ValueError`` when the distortion has no unique inverse over the film.
    """
    lens = None if distortion is None or distortion.is_zero else distortion
    if lens is None and camera.fx == camera.fy:
        return FreeView(camera=camera, distortion=None, rendered=camera)
    warp = _warp(camera, lens)
    rendered = _rendered_pinhole(camera, warp.focal, warp.width, warp.height, warp.cx, warp.cy)
    return FreeView(
        camera=camera, distortion=lens, rendered=rendered, map_x=warp.map_x, map_y=warp.map_y
    )
