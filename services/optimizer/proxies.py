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

from services.optimizer.geometry import FloatArray, PinholeCameras

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

    Returns ``(2, ...)`` = ``(a_-, a_+)``, NaN unless the sphere lies wholly in front
    (``C_z > ρ``).
    """
    denom = depth**2 - radius**2
    disc = lateral**2 + denom
    ok = (depth > radius) & (disc > 0.0)
    root = radius * np.sqrt(disc, out=np.ones_like(disc), where=ok)
    centre = lateral * depth
    out = np.empty((2,) + disc.shape)
    np.subtract(centre, root, out=out[0])
    np.add(centre, root, out=out[1])
    np.divide(out, denom, out=out, where=ok)
    np.copyto(out, np.nan, where=~ok)
    return out


def _camera_frame(cameras: PinholeCameras, points: FloatArray) -> FloatArray:
    """Camera coordinates ``(3, P, N)`` of world points ``(P, 3)``, ``o + Σ_j p_j e_j``
    (:attr:`.geometry.PinholeCameras.frame`). Elementwise, so a point's coordinates do not depend on
    the other points (the Gauss–Newton solve of :mod:`.mapping` batches its finite
    differences). PinholeCameras last: the grid's are many, the points few."""
    origin, axes = cameras.frame
    cam: FloatArray = (
        origin[:, np.newaxis, :]
        + axes[:, 0, np.newaxis, :] * points[:, 0, np.newaxis]
        + axes[:, 1, np.newaxis, :] * points[:, 1, np.newaxis]
        + axes[:, 2, np.newaxis, :] * points[:, 2, np.newaxis]
    )
    return cam


def _to_pixels(cameras: PinholeCameras, bounds: FloatArray) -> FloatArray:
    """Boxes ``(N, M, 4)`` from the bounds ``(4, M, N)`` ``(x_lo, y_lo, x_hi, y_hi)`` of
    normalised coordinates (NaN stays NaN)."""
    centre = np.array([cameras.cx, cameras.cy, cameras.cx, cameras.cy])
    boxes: FloatArray = cameras.focal_px * bounds.T + centre
    return boxes


def _sphere_bounds(cameras: PinholeCameras, centres: FloatArray, radii: FloatArray) -> FloatArray:
    """Normalised bounds ``(4, M, N)`` (:func:`_to_pixels`) of spheres ``(M, 3)`` / ``(M,)``."""
    cam = _camera_frame(cameras, centres)
    bounds = _tangent_bounds(cam[:2], cam[2], radii[:, np.newaxis])  # (lo/hi, x/y, M, N)
    return bounds.reshape((4,) + bounds.shape[2:])


def sphere_boxes(cameras: PinholeCameras, centres: ArrayLike, radii: ArrayLike) -> FloatArray:
    """Exact image boxes ``(N, M, 4)`` of spheres ``(M, 3)`` / ``(M,)`` in every camera.

    Uses :func:`_tangent_bounds` on the camera-frame centre for the horizontal (x) and vertical
    (y) image axes. The box is not centred on the projected centre: under perspective the
    silhouette is an ellipse whose centre lies farther from the principal point than the
    projected centre, by ``≈ a (ρ/C_z)²`` in normalised units (see :mod:`.mapping`).
    """
    points = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    rho = np.broadcast_to(np.asarray(radii, dtype=np.float64), len(points))
    return _to_pixels(cameras, _sphere_bounds(cameras, points, rho))


_ANGLES: Final = np.linspace(0.0, 2.0 * math.pi, RIM_POINTS, endpoint=False)
_COS: Final = np.cos(_ANGLES)[:, np.newaxis]
_SIN: Final = np.sin(_ANGLES)[:, np.newaxis]
_CHUNK_SAMPLES: Final = 262_144
"""Rim samples (points × rims × cameras) per pass: long inner loops over the cameras (which
matter more than cache-sized temporaries), yet bounded temporaries however large the grid."""
_SPHERE: Final = ProxyKind.SPHERE.value  # plain ints: comparing arrays with enums is slow
_CONE: Final = ProxyKind.CONE.value


def _solid_bounds(
    cameras: PinholeCameras, kinds: NDArray[np.int_], params: FloatArray
) -> FloatArray:
    """Normalised bounds ``(4, M, N)`` (:func:`_to_pixels`) of prisms and cones: bounds of their
    projected rim samples, NaN unless every sample lies in front of the camera.

    Every solid has two rims, its base and its top; a cone's top is a rim of radius 0, its
    apex. Rim sample ``k`` of a rim centred at ``C`` (camera coordinates) is
    ``C + ρ (cos a_k e_x + sin a_k e_y)``, with ``e_x``, ``e_y`` the world's horizontal axes
    in camera coordinates: the camera-frame ring is built once per camera, and each sample
    costs a multiply-add per coordinate. The bounds are taken over the normalised coordinates
    ``x/z``, ``y/z`` and scaled to pixels afterwards (``f a + c`` is increasing in ``a``).
    """
    n, m = len(cameras), len(params)
    rims = np.empty((2, m, 3))
    rims[:, :, :2] = params[:, :2]
    rims[0, :, 2] = 0.0
    rims[1, :, 2] = params[:, 3]
    # Samples are (3, rim × K, M, c) for a pass of c cameras: both rims' samples lead, so the
    # bounds reduce over one outer axis, and the cameras run along the fast inner axis.
    centres = _camera_frame(cameras, rims.reshape(2 * m, 3)).reshape(3, 2, 1, m, n)
    radii = np.empty((2, m))
    radii[:] = params[:, 2]
    radii[1, kinds == _CONE] = 0.0
    axes = cameras.frame[1]
    ring = _COS * axes[:, 0, np.newaxis, :] + _SIN * axes[:, 1, np.newaxis, :]  # (3, K, N)
    radii, ring = radii[:, np.newaxis, :, np.newaxis], ring[:, np.newaxis, :, np.newaxis, :]
    # Rounding is monotonic, so the least sample depth of a rim is that of its least ring depth.
    near = (radii * ring[2].min(axis=1) + centres[2]).min(axis=0)[0]  # (M, N)
    bounds = np.empty((2, 2, m, n))  # (lo/hi, x/y, solid, camera)
    step = max(1, _CHUNK_SAMPLES // (2 * m * RIM_POINTS))
    with np.errstate(divide="ignore", invalid="ignore"):  # samples behind: NaN below anyway
        for start in range(0, n, step):
            part = slice(start, start + step)
            samples = radii * ring[..., part]
            samples += centres[..., part]
            samples = samples.reshape(3, 2 * RIM_POINTS, m, -1)
            ratio = np.divide(samples[:2], samples[2], out=samples[:2])
            np.minimum.reduce(ratio, axis=1, out=bounds[0, :, :, part])
            np.maximum.reduce(ratio, axis=1, out=bounds[1, :, :, part])
    np.copyto(bounds, np.nan, where=~(near > 0.0))
    return bounds.reshape(4, m, n)


def proxy_boxes(cameras: PinholeCameras, kinds: ArrayLike, params: ArrayLike) -> FloatArray:
    """Unclipped image boxes ``(N, M, 4)`` ``[x1, y1, x2, y2]`` of proxies in every camera.

    Parameters
    ----------
    cameras : PinholeCameras
        N cameras.
    kinds : array_like of int, shape (M,)
        :class:`ProxyKind` of each object.
    params : array_like, shape (M, 4)
        ``(x, y, ρ, H)``: footprint centre, footprint half-width and height, scene units.

    Returns
    -------
    ndarray, shape (N, M, 4)
        Pixel boxes; NaN where a proxy is not wholly in front of the camera. Each object's box
        is computed independently of the others (to the last bit).
    """
    kind = np.asarray(kinds, dtype=np.int_)
    par = np.asarray(params, dtype=np.float64).reshape(-1, 4)
    spheres = kind == _SPHERE
    if spheres.all():
        bounds = _sphere_bounds(cameras, par[:, :3], par[:, 2])
    elif not spheres.any():
        bounds = _solid_bounds(cameras, kind, par)
    else:
        bounds = np.empty((4, len(par), len(cameras)))
        balls, solids = par[spheres], ~spheres
        bounds[:, spheres] = _sphere_bounds(cameras, balls[:, :3], balls[:, 2])
        bounds[:, solids] = _solid_bounds(cameras, kind[solids], par[solids])
    return _to_pixels(cameras, bounds)


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
    # minimum(maximum()) is np.clip without its Python wrapper (NaN stays NaN in both).
    clipped = np.minimum(np.maximum(b, 0.0), np.array([width, height, width, height]))
    area = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    kept = (clipped[..., 2] - clipped[..., 0]) * (clipped[..., 3] - clipped[..., 1])
    # Only positive areas divide: NaN boxes have a NaN area, so no fraction comes out NaN.
    inside = np.divide(kept, area, out=np.zeros_like(area), where=area > 0.0)
    clipped[~(inside > 0.0)] = np.nan
    return clipped, inside
