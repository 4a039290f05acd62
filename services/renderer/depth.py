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

The same rays give the view's **outline shading** ``S``: the surface's albedo lit by a light at
the camera, with no shadows,

    S = ρ̄ · |n · d|,        d = (c - p) / ‖c - p‖

(``ρ̄`` the albedo's mean over RGB, ``n`` the shading normal, ``c`` the camera centre), sRGB
encoded to 8 bits. Its edges are the ones any light shows: silhouettes, creases (``n`` jumps)
and texture (``ρ̄`` jumps), and none of the scene light's cast shadows or terminators, which move
with the light; a photo's light is never the model's.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.depth_archive import DEPTH_MEDIA_TYPE, DepthImage
from services.renderer.free_view import FreeView
from services.renderer.imaging import linear_to_srgb8

__all__ = ["DEPTH_MEDIA_TYPE", "GEOMETRY_AOVS", "DepthImage", "depth_image", "outline_shading"]

GEOMETRY_AOVS: Final = "dd.y:depth,p:position,si:shape_index,a:albedo,n:sh_normal"
"""The aov integrator's channels: ray distance (0 on a miss), world position, shape key,
albedo (RGB), shading normal (world)."""


def outline_shading(
    channels: NDArray[np.float32], centre: NDArray[np.float64]
) -> NDArray[np.uint8]:
    """The outline shading ``S`` (module docstring) of a :data:`GEOMETRY_AOVS` render ``(h, w,
    11)`` seen from the camera centre ``centre``; 0 where the ray hits nothing."""
    hit = channels[..., 0] > 0.0
    towards = np.asarray(centre, dtype=np.float32) - channels[..., 1:4]
    length = np.sqrt(np.einsum("ijk,ijk->ij", towards, towards))
    facing = np.abs(np.einsum("ijk,ijk->ij", channels[..., 8:11], towards))
    albedo = channels[..., 5:8].mean(axis=-1)
    lit = albedo * facing / np.maximum(length, np.float32(1e-12))
    return linear_to_srgb8(np.where(hit, lit, np.float32(0.0)))


def depth_image(
    channels: NDArray[np.float32], shape_to_object: NDArray[np.int64], view: FreeView
) -> DepthImage:
    """The view's :class:`DepthImage` (with its outline shading) from the ``(h, w, 11)``
    :data:`GEOMETRY_AOVS` render of its rendered pinhole (module docstring)."""
    rendered = view.rendered
    hit = channels[..., 0] > 0.0
    rotation = np.asarray(rendered.rotation, dtype=np.float64)
    z = channels[..., 1:4].astype(np.float64) @ rotation[2] + rendered.translation[2]
    depth = np.where(hit, z, 0.0).astype(np.float32)
    keys = np.rint(channels[..., 4]).astype(np.int64)
    known = hit & (keys >= 0) & (keys < len(shape_to_object))
    objects = np.where(known, shape_to_object[np.where(known, keys, 0)], -1).astype(np.float32)
    centre = -rotation.T @ np.asarray(rendered.translation, dtype=np.float64)
    shading = outline_shading(channels, centre).astype(np.float32)
    return DepthImage(
        depth=view.warp(depth, nearest=True),
        objects=np.rint(view.warp(objects, nearest=True)).astype(np.int16),
        shading=np.rint(view.warp(shading)).astype(np.uint8),
    )
