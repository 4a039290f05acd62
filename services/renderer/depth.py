"""Per-pixel depth and object ids of a view: the geometry a dense refinement back-projects the
render's edges through (issue 23, "confirmation and dense refinement by one render").

One ray through each pixel centre of the rendered pinhole (the mask sensor) with Mitsuba's
``aov`` integrator, :data:`GEOMETRY_AOVS`: the surface point ``p`` (world) and the shape hit.
The depth of a pixel is its surface point's distance along the optical axis, OpenCV's ``Z_c``::

    Z_c = r₃ · p + t₃        (r₃ the third row of R, world to camera; t = -R c)

so a pixel (u, v) (centre at ``(j + ½, i + ½)``) goes back to the camera point
``Z_c ((u - cx) / fx, (v - cy) / fy, 1)`` (undistorted coordinates when the camera has a lens).
``Z_c`` does not change between the rendered pinhole and the image of a distorted camera (same
pose), so the image's depth is the rendered one resampled by the view's warp, nearest pixel.
0 where the ray hits nothing.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.depth_archive import DEPTH_MEDIA_TYPE, DepthImage
from services.renderer.free_view import FreeView

__all__ = ["DEPTH_MEDIA_TYPE", "GEOMETRY_AOVS", "DepthImage", "depth_image"]

GEOMETRY_AOVS: Final = "dd.y:depth,p:position,si:shape_index"
"""The aov integrator's channels: ray distance (0 on a miss), world position, shape key."""


def depth_image(
    channels: NDArray[np.float32], shape_to_object: NDArray[np.int64], view: FreeView
) -> DepthImage:
    """The view's :class:`DepthImage` from the ``(h, w, 5)`` :data:`GEOMETRY_AOVS` render of its
    rendered pinhole (module docstring)."""
    rendered = view.rendered
    hit = channels[..., 0] > 0.0
    rotation = np.asarray(rendered.rotation, dtype=np.float64)
    z = channels[..., 1:4].astype(np.float64) @ rotation[2] + rendered.translation[2]
    depth = np.where(hit, z, 0.0).astype(np.float32)
    keys = np.rint(channels[..., 4]).astype(np.int64)
    known = hit & (keys >= 0) & (keys < len(shape_to_object))
    objects = np.where(known, shape_to_object[np.where(known, keys, 0)], -1).astype(np.float32)
    return DepthImage(
        depth=view.warp(depth, nearest=True),
        objects=np.rint(view.warp(objects, nearest=True)).astype(np.int16),
    )
