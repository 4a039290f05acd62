"""Object proxies: the simple solids the optimizer uses to predict where an object's box appears.

A mapped object is one of three upright proxies standing on the ground (z = 0), described by its
footprint centre ``(x, y)``, its footprint half-width ``ρ`` and its height ``H``:

``SPHERE``
    A ball of radius ρ centred at ``(x, y, ρ)`` (H = 2ρ). Its image box is computed exactly from
    the four planes through the camera centre that touch it (:func:`sphere_boxes`).
``PRISM``
    An upright cylinder of radius ρ and height H. Stands for cylinders, cubes (a square footprint
    of side s turned by any yaw α has the same extent ``(s/2)(|cos α| + |sin α|)`` along the view
    direction and across it, so a cylinder of that radius has the cube's footprint extents) and
    meshes (whose shape the optimizer does not know).
``CONE``
    An upright cone of base radius ρ and apex height H.

Prism and cone boxes are the bounds of their rims (and apex) sampled at :data:`RIM_POINTS`
points, which approximates a circle to within ``ρ (1 - cos(π / RIM_POINTS))`` (0.5 % of ρ).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.optimizer.geometry import Cameras, FloatArray

__all__ = [
    "RIM_POINTS",
    "ProxyKind",
    "clip_boxes",
    "kind_of",
    "proxy_boxes",
    "sphere_boxes",
]

RIM_POINTS: Final = 32


class ProxyKind(IntEnum):
    """The solid standing in for an object class."""

    SPHERE = 0
    PRISM = 1
    CONE = 2


_KINDS: Final = {"sphere": ProxyKind.SPHERE, "cone": ProxyKind.CONE}


def kind_of(label: str) -> ProxyKind:
    """The proxy of a detector class: sphere and cone have their own; everything else is a
    prism (cylinder, cube, mesh and classes the optimizer does not know)."""
    return _KINDS.get(label, ProxyKind.PRISM)


def _tangent_bounds(lateral: FloatArray, depth: FloatArray, radius: FloatArray) -> FloatArray:
    """Normalised image coordinates of the two planes through the camera centre that touch a
    sphere, along one image axis.

    A plane through the camera centre containing the image line ``x/z = a`` has unit normal
    ``(1, 0, -a)/√(1 + a²)``; it touches the sphere of radius ρ centred at ``C`` when
    ``(C_x - a C_z)² = ρ² (1 + a²)``, a quadratic in ``a`` with roots

    .. math:: a_\\pm = \\frac{C_x C_z \\pm ρ \\sqrt{C_x^2 + C_z^2 - ρ^2}}{C_z^2 - ρ^2}.

    Returns ``(..., 2)`` = ``(a_-, a_+)``, NaN unless the sphere lies wholly in front
    (``C_z > ρ``).
    """
    denom = depth**2 - radius**2
    disc = lateral**2 + denom
    ok = (depth > radius) & (disc > 0.0)
    root = radius * np.sqrt(np.where(ok, disc, 1.0))
    safe = np.where(ok, denom, 1.0)
    lo = (lateral * depth - root) / safe
    hi = (lateral * depth + root) / safe
    out = np.stack([lo, hi], axis=-1)
    out[~ok] = np.nan
    return out


def sphere_boxes(cameras: Cameras, centres: ArrayLike, radii: ArrayLike) -> FloatArray:
    """Exact image boxes ``(N, M, 4)`` of spheres ``(M, 3)`` / ``(M,)`` in every camera.

    Uses :func:`_tangent_bounds` on the camera-frame centre for the horizontal (x) and vertical
    (y) image axes. The box is not centred on the projected centre: under perspective the
    silhouette is an ellipse whose centre lies farther from the principal point than the
    projected centre, by ``≈ a (ρ/C_z)²`` in normalised units (see :mod:`.mapping`).
    """
    cam = cameras.to_camera(centres)
    rho = np.broadcast_to(np.asarray(radii, dtype=np.float64), cam.shape[:-1])
    ax = _tangent_bounds(cam[..., 0], cam[..., 2], rho)
    ay = _tangent_bounds(cam[..., 1], cam[..., 2], rho)
    f = cameras.focal_px
    return np.stack(
        [
            f * ax[..., 0] + cameras.cx,
            f * ay[..., 0] + cameras.cy,
            f * ax[..., 1] + cameras.cx,
            f * ay[..., 1] + cameras.cy,
        ],
        axis=-1,
    )


_ANGLES: Final = np.linspace(0.0, 2.0 * math.pi, RIM_POINTS, endpoint=False)
_RIM: Final = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=-1)


def _solid_points(kinds: NDArray[np.int_], params: FloatArray) -> FloatArray:
    """Sample points ``(M, 2K, 3)`` of prisms (two rims) and cones (base rim and apex)."""
    x, y, rho, height = (params[:, i] for i in range(4))
    ring = _RIM[np.newaxis] * rho[:, np.newaxis, np.newaxis] + np.stack([x, y], -1)[:, None]
    bottom = np.concatenate([ring, np.zeros(ring.shape[:-1] + (1,))], axis=-1)
    top = np.concatenate([ring, np.broadcast_to(height[:, None, None], bottom[..., :1].shape)], -1)
    apex = np.stack([x, y, height], axis=-1)[:, np.newaxis, :]
    cone = (kinds == ProxyKind.CONE)[:, np.newaxis, np.newaxis]
    top = np.where(cone, np.broadcast_to(apex, top.shape), top)
    return np.concatenate([bottom, top], axis=1)


def proxy_boxes(cameras: Cameras, kinds: ArrayLike, params: ArrayLike) -> FloatArray:
    """Unclipped image boxes ``(N, M, 4)`` ``[x1, y1, x2, y2]`` of proxies in every camera.

    Parameters
    ----------
    cameras : Cameras
        N cameras.
    kinds : array_like of int, shape (M,)
        :class:`ProxyKind` of each object.
    params : array_like, shape (M, 4)
        ``(x, y, ρ, H)``: footprint centre, footprint half-width and height, scene units.

    Returns
    -------
    ndarray, shape (N, M, 4)
        Pixel boxes; NaN where a proxy is not wholly in front of the camera.
    """
    kind = np.asarray(kinds, dtype=np.int_)
    par = np.asarray(params, dtype=np.float64).reshape(-1, 4)
    boxes = np.full((len(cameras), par.shape[0], 4), np.nan)
    spheres = kind == ProxyKind.SPHERE
    if spheres.any():
        p = par[spheres]
        centres = np.stack([p[:, 0], p[:, 1], p[:, 2]], axis=-1)
        boxes[:, spheres] = sphere_boxes(cameras, centres, p[:, 2])
    if (~spheres).any():
        pts = _solid_points(kind[~spheres], par[~spheres])
        m, k = pts.shape[:2]
        pixels, _ = cameras.project(pts.reshape(-1, 3))
        # (N, M, 2, K) in memory, so min/max run along the contiguous axis: ~10x faster than
        # reducing the strided sample axis of (N, M, K, 2), and exactly the same values.
        pixels = np.ascontiguousarray(pixels.reshape(len(cameras), m, k, 2).transpose(0, 1, 3, 2))
        boxes[:, ~spheres] = np.concatenate([pixels.min(axis=-1), pixels.max(axis=-1)], axis=-1)
    return boxes


def clip_boxes(boxes: ArrayLike, width: float, height: float) -> tuple[FloatArray, FloatArray]:
    """Boxes clipped to the image ``[0, W] × [0, H]`` and the fraction of each box inside it.

    Returns
    -------
    clipped : ndarray, shape (..., 4)
        NaN where the box misses the image or was NaN.
    inside : ndarray, shape (...)
        Clipped area over full area, 0 for missing boxes.
    """
    b = np.asarray(boxes, dtype=np.float64)
    lo = np.array([0.0, 0.0, 0.0, 0.0])
    hi = np.array([width, height, width, height])
    clipped = np.clip(b, lo, hi)
    area = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    kept = (clipped[..., 2] - clipped[..., 0]) * (clipped[..., 3] - clipped[..., 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = np.where(area > 0.0, kept / area, 0.0)
    inside = np.nan_to_num(inside, nan=0.0)
    clipped[~(inside > 0.0)] = np.nan
    return clipped, inside
