"""Oriented edges for the dense refinement (:mod:`.dense`): the render's edge pixels
back-projected through its depth to world points, and the target's pyramid of truncated oriented
distance maps, sampled bilinearly.

Both images go through the same detector (:func:`image_edges`: Canny after a blur, each edge
pixel with its gradient-orientation bin), so a model edge and the target edge it should meet are
located alike. A level's map ``D_b`` is, for orientation bin ``b``, the exact Euclidean distance
(``cv2.distanceTransform``) to the nearest target edge in bin ``b`` or a neighbour, truncated
at ``τ`` (oriented chamfer matching: clutter running across an edge does not pull it).

The model keeps only the render's edges that lie on its **outline** (within :data:`OUTLINE_PX`,
:func:`outline`): object silhouettes and occlusions from the render's object ids and depth, and
creases and texture from its outline shading (:mod:`services.renderer.depth`: the albedo lit
from the camera, no shadows). Its cast shadows and shading terminators go: they are where the
scene file's light puts them, and a photo's light is never that one. The target keeps all its
edges; its own shadows are clutter, which the truncated oriented distance tolerates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.geometry.camera import PinholeCamera
from services.common.geometry.free_camera import LensDistortion
from services.optimizer.free.refine import Intrinsics
from services.optimizer.geometry import FloatArray

__all__ = [
    "BLUR_SIGMA_PX",
    "CANNY_PX",
    "MAX_POINTS",
    "MIN_SPAN",
    "OUTLINE_PX",
    "SPAN_PERCENTILES",
    "DEPTH_JUMP",
    "outline",
    "ORIENTATION_BINS",
    "EdgePoints",
    "Level",
    "bilinear",
    "camera_matrix",
    "bilinear_corners",
    "edge_points",
    "edge_chance",
    "edge_points_by_outline",
    "exact_distance",
    "gray",
    "image_edges",
    "with_contrast",
    "lens_coefficients",
    "on_film",
    "target_level",
]

ORIENTATION_BINS: Final = 8
"""Edge orientations are told apart in bins of 180° / 8 = 22.5° (a bin and its neighbours
match: ±34° at most)."""
BLUR_SIGMA_PX: Final = 1.5
"""Gaussian blur before the gradients: JPEG blocks and sensor noise stay under the thresholds."""
CANNY_PX: Final = (30.0, 80.0)
"""Canny's hysteresis thresholds on the 3x3 Sobel gradient magnitude (a step of h grey levels
gives about 4h): edges of steps above ~12 levels, seeded by steps above ~5."""
MIN_SPAN: Final = 100.0
"""The least grey span (between the 0.5th and 99.5th percentiles) a target is brought to before
its edges are found (:func:`with_contrast`): Canny's thresholds are levels, and a photo's
exposure, haze or tone curve can squeeze the steps the render shows. A drone photo of the demo
(``cosmos bench --free ... --seed 43 --target-width 1280 --fov-range 1.5,2.2``, #1 ``photo``,
its fov given) spans 60 levels: its ground's border fell under the thresholds, the render's
border had nothing to meet, and the dense fit went from 8 % of the radius off to 32 %.
Stretched, it ends 2.9 % off. The renders of ``benchmarks.dense_light``'s 40 cases span 115
levels or more, their clean targets 111 or more; at 150, a quarter of those were stretched too,
and one clean fit of 40 fell outside 5 %/2°."""
SPAN_PERCENTILES: Final = (0.5, 99.5)
"""The percentiles between which a grey image's span is taken: a few specular or black pixels
do not count."""
OUTLINE_PX: Final = 2
"""How far (Chebyshev, pixels) a render edge may lie from the outline and still be the same
edge: the ids, depth and shading are sampled once at each pixel centre (±½ px), the colours are
antialiased, and both images are blurred by :data:`BLUR_SIGMA_PX` before Canny."""
DEPTH_JUMP: Final = 0.1
"""A relative depth step across a 3x3 neighbourhood that is an occlusion, not a surface seen
obliquely (a plane at 10° grazing, 300 px focal: ~4 % across two pixels)."""
MAX_POINTS: Final = 2000
"""Model edge points kept (evenly spaced along the edge pixels' raster order)."""


@dataclass(frozen=True)
class EdgePoints:
    """Model edge points: ``world`` ``(N, 3)`` in scene units and their image-edge orientation
    bins ``bins`` ``(N,)`` (:data:`ORIENTATION_BINS`)."""

    world: FloatArray
    bins: NDArray[np.intp]


def image_edges(gray: NDArray[np.uint8]) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """Canny edges of an 8-bit grey image (after a :data:`BLUR_SIGMA_PX` blur) and each pixel's
    gradient-orientation bin (``⌊(atan2(g_y, g_x) mod π) / (π / B)⌋``, B =
    :data:`ORIENTATION_BINS`)."""
    blurred = cv2.GaussianBlur(gray, (0, 0), BLUR_SIGMA_PX)
    gx = cv2.Sobel(blurred, cv2.CV_16S, 1, 0, ksize=3)
    gy = cv2.Sobel(blurred, cv2.CV_16S, 0, 1, ksize=3)
    edges = cv2.Canny(gx, gy, CANNY_PX[0], CANNY_PX[1], L2gradient=True) > 0
    angle = np.mod(np.arctan2(gy.astype(np.float32), gx.astype(np.float32)), np.pi)
    bins = np.minimum((angle / (np.pi / ORIENTATION_BINS)).astype(np.intp), ORIENTATION_BINS - 1)
    return edges, bins


def gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """``image`` as 8-bit grey (RGB converted; grey as it is)."""
    if image.ndim == 2:
        return image
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def with_contrast(gray: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """``gray`` stretched about the middle of its span ``[p, q]`` (:data:`SPAN_PERCENTILES`) so
    that the span is at least :data:`MIN_SPAN`: ``g' = m + (g - m) · MIN_SPAN / (q - p)``, ``m``
    = (p + q) / 2, clipped to 0–255; as it is when the span already is (or is flat)."""
    counts = np.cumsum(np.bincount(gray.ravel(), minlength=256))
    low, high = (
        int(np.searchsorted(counts, share / 100.0 * counts[-1])) for share in SPAN_PERCENTILES
    )
    span = high - low
    if span >= MIN_SPAN or span < 1:
        return gray
    middle = 0.5 * (low + high)
    table = np.clip(np.rint(middle + (np.arange(256) - middle) * MIN_SPAN / span), 0, 255)
    return np.asarray(table.astype(np.uint8)[gray], dtype=np.uint8)


def on_film(gray: NDArray[np.uint8], film: tuple[int, int]) -> NDArray[np.uint8]:
    """``gray`` brought to ``film`` ``(w, h)``: shrunk by ``cv2.INTER_AREA``, enlarged by
    ``cv2.INTER_CUBIC`` (a small photo's edges, found on the enlarged grey, fall between its own
    pixels), as it is when already that size."""
    if gray.shape[:2] == (film[1], film[0]):
        return gray
    how = cv2.INTER_CUBIC if film[0] > gray.shape[1] else cv2.INTER_AREA
    return np.asarray(cv2.resize(gray, film, interpolation=how), dtype=np.uint8)


def camera_matrix(k: Intrinsics, scale: float = 1.0) -> FloatArray:
    """The 3x3 camera matrix of ``k`` on a film downsampled ``scale`` times."""
    return np.array(
        [[k.fx / scale, 0.0, k.cx / scale], [0.0, k.fy / scale, k.cy / scale], [0.0, 0.0, 1.0]]
    )


def lens_coefficients(distortion: LensDistortion | None) -> FloatArray:
    """OpenCV's ``(k1, k2, p1, p2, k3)`` of the lens (zeros without one)."""
    return np.zeros(5) if distortion is None else distortion.coefficients()


def edge_points(
    render_rgb: NDArray[np.uint8],
    render_depth: NDArray[np.float32],
    camera: PinholeCamera,
    distortion: LensDistortion | None = None,
) -> EdgePoints:
    """The render's edge pixels back-projected through its depth to world points, at most
    :data:`MAX_POINTS` (near its outline, and off it: :func:`edge_points_by_outline`)."""
    edges, bins = image_edges(gray(render_rgb))
    return _back_projected(edges, bins, _nearest_depth(render_depth), camera, distortion)


def edge_points_by_outline(
    render_rgb: NDArray[np.uint8],
    render_depth: NDArray[np.float32],
    camera: PinholeCamera,
    distortion: LensDistortion | None,
    near: NDArray[np.bool_],
) -> tuple[EdgePoints, EdgePoints]:
    """:func:`edge_points` ``near`` the outline and off it, from one pass of the detector."""
    edges, bins = image_edges(gray(render_rgb))
    nearest = _nearest_depth(render_depth)
    on, off = (_back_projected(edges & m, bins, nearest, camera, distortion) for m in (near, ~near))
    return on, off


def _nearest_depth(render_depth: NDArray[np.float32]) -> NDArray[np.float32]:
    """Each pixel's smallest depth in its 3x3 neighbourhood (inf where no surface): an edge at a
    silhouette belongs to the nearer, occluding surface."""
    depth = np.where(render_depth > 0.0, render_depth, np.inf).astype(np.float32)
    return np.asarray(
        cv2.erode(depth, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE),
        dtype=np.float32,
    )


def _back_projected(
    edges: NDArray[np.bool_],
    bins: NDArray[np.intp],
    nearest: NDArray[np.float32],
    camera: PinholeCamera,
    distortion: LensDistortion | None,
) -> EdgePoints:
    """The ``edges`` pixels (at most :data:`MAX_POINTS`, evenly spaced) back-projected through
    the ``nearest`` depth to world points, with their orientation bins."""
    rows, cols = np.nonzero(edges & np.isfinite(nearest))
    if rows.size > MAX_POINTS:
        keep = np.linspace(0, rows.size - 1, MAX_POINTS).round().astype(np.intp)
        rows, cols = rows[keep], cols[keep]
    pixels = np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float64)
    k = Intrinsics(camera.fx, camera.fy, camera.cx, camera.cy)
    normalised = cv2.undistortPoints(
        pixels.reshape(-1, 1, 2), camera_matrix(k), lens_coefficients(distortion)
    ).reshape(-1, 2)
    z = nearest[rows, cols].astype(np.float64)[:, None]
    in_camera = np.hstack([normalised * z, z])
    rotation = np.asarray(camera.rotation, dtype=np.float64)
    world = (in_camera - np.asarray(camera.translation)) @ rotation
    return EdgePoints(world=world, bins=bins[rows, cols])


def outline(
    depth: NDArray[np.float32], objects: NDArray[np.int16], shading: NDArray[np.uint8]
) -> NDArray[np.bool_]:
    """The pixels within :data:`OUTLINE_PX` of the render's outline (module docstring): where
    the object id changes or the depth steps by :data:`DEPTH_JUMP` in a 3x3 neighbourhood (0,
    no surface, counts as a step), and the Canny edges of its outline ``shading``."""
    square = np.ones((3, 3), np.uint8)
    ids = objects.astype(np.int16)
    edge = cv2.dilate(ids, square) != cv2.erode(ids, square)
    far = np.where(depth > 0.0, depth, np.float32(1e9)).astype(np.float32)
    top, bottom = cv2.dilate(far, square), cv2.erode(far, square)
    edge |= top > bottom * (1.0 + DEPTH_JUMP)
    edge |= image_edges(shading)[0]
    size = 2 * OUTLINE_PX + 1
    return np.asarray(cv2.dilate(edge.astype(np.uint8), np.ones((size, size), np.uint8)) > 0)


def exact_distance(distance: ArrayLike) -> NDArray[np.float32]:
    """``cv2.distanceTransform``'s exact Euclidean distances made the same on every call: they
    are distances between pixel centres, ``d² = dx² + dy²`` an integer, but OpenCV's threads
    leave their last float32 bit varying (52 of 180 repeated calls differed), and with it which
    local minimum a fit ends in. ``√rint(d²)`` restores the exact value."""
    squared = np.square(np.asarray(distance, dtype=np.float64))
    return np.asarray(np.sqrt(np.rint(squared)), dtype=np.float32)


@dataclass(frozen=True)
class Level:
    """One pyramid level of the target: truncated oriented distance maps and their gradients,
    ``(B, h, w)`` each, in pixels of the level."""

    scale: int
    sigma: float
    cap: float
    distance: NDArray[np.float32]
    grad_x: NDArray[np.float32]
    grad_y: NDArray[np.float32]

    def arrays(self) -> tuple[NDArray[np.float32], ...]:
        """The maps and their gradients."""
        return self.distance, self.grad_x, self.grad_y


def target_level(gray: NDArray[np.uint8], scale: int, sigma: float, cap: float) -> Level:
    """The target ``gray`` downsampled ``scale`` times: its truncated oriented distance maps
    (truncation ``cap``) and their gradients, with the level's soft-L1 scale ``sigma``.

    The maps are :func:`exact_distance`'s, truncated, and the gradients ``np.gradient``'s
    (central differences, one-sided on the border), bit for bit; both are computed in float32
    in place, on distances first clipped just above ``cap`` (so every ``d²`` is a small
    integer, exact in float32): a quarter faster (``python -m benchmarks.target_maps``, one
    run: 10.3 → 7.9 ms a full-resolution level at 320 x 240, 53 → 40 ms at 640 x 480)."""
    height, width = gray.shape
    size = (max(width // scale, 8), max(height // scale, 8))
    small = gray
    if scale > 1:
        small = np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    edges, bins = image_edges(small)
    distance = np.empty((ORIENTATION_BINS, *small.shape), dtype=np.float32)
    above = np.float32(cap + 1.0)
    for b in range(ORIENTATION_BINS):
        near = (bins == b) | (bins == (b + 1) % ORIENTATION_BINS)
        near |= bins == (b - 1) % ORIENTATION_BINS
        free = np.where(edges & near, 0, 255).astype(np.uint8)
        d = distance[b]
        cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE, dst=d)
        # √rint(d²) as exact_distance takes it, on d ≤ cap + 1 (beyond, √ stays above cap)
        np.minimum(d, above, out=d)
        np.multiply(d, d, out=d)
        np.rint(d, out=d)
        np.sqrt(d, out=d)
        np.minimum(d, np.float32(cap), out=d)
    grad_x, grad_y = _gradients(distance)
    return Level(scale, sigma, cap, distance, grad_x, grad_y)


def _gradients(maps: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """``np.gradient(maps, axis=(2, 1))`` of ``(B, h, w)`` float32 maps (h, w ≥ 2), bit for
    bit, without its temporaries: ``(f[i+1] - f[i-1]) / 2`` inside, ``f[1] - f[0]`` and
    ``f[-1] - f[-2]`` on the border."""
    gx = np.empty_like(maps)
    gy = np.empty_like(maps)
    for out, axis in ((gx, 2), (gy, 1)):
        n = maps.shape[axis]

        def cut(start: int | None, stop: int | None, axis: int = axis) -> tuple[slice, ...]:
            return (slice(None),) * axis + (slice(start, stop),)

        np.subtract(maps[cut(2, None)], maps[cut(None, -2)], out=out[cut(1, -1)])
        np.divide(out[cut(1, -1)], np.float32(2.0), out=out[cut(1, -1)])
        np.subtract(maps[cut(1, 2)], maps[cut(0, 1)], out=out[cut(0, 1)])
        np.subtract(maps[cut(n - 1, n)], maps[cut(n - 2, n - 1)], out=out[cut(n - 1, n)])
    return gx, gy


def edge_chance(level: Level, bins: NDArray[np.intp], radius: float) -> float:
    """The share of edge points of orientations ``bins`` that would lie within ``radius``
    pixels of a target edge of their orientation if they were placed at random on the film:
    ``(1/N) Σᵢ p_{bᵢ}``, ``p_b`` the share of the level's pixels where ``D_b ≤ radius``. About
    0.02 on a rendered target; 0.5 on one under a strong noise texture, where a wrong pose's
    points found edges as often as a right one's (``above_chance`` in the contract)."""
    if len(bins) == 0:
        return 0.0
    near = (level.distance <= radius).reshape(len(level.distance), -1).mean(axis=1)
    return float(min(np.mean(near[bins]), 0.99))


def bilinear_corners(
    level: Level, bins: NDArray[np.intp], uv: FloatArray
) -> tuple[tuple[NDArray[np.intp], ...], tuple[FloatArray, ...], NDArray[np.bool_]]:
    """The flat indices and bilinear weights of the four grid neighbours of the continuous pixel
    positions ``uv`` (corner origin) of the level, and which lie on the film."""
    _, height, width = level.distance.shape
    col, row = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    inside = (col >= 0) & (col <= width - 1) & (row >= 0) & (row <= height - 1)
    col = np.clip(np.where(inside, col, 0.0), 0.0, width - 1.001)
    row = np.clip(np.where(inside, row, 0.0), 0.0, height - 1.001)
    c0, r0 = col.astype(np.intp), row.astype(np.intp)
    fc, fr = col - c0, row - r0
    first = (bins * height + r0) * width + c0  # flat index of the top-left neighbour
    corners = (first, first + 1, first + width, first + width + 1)
    weights = ((1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr)
    return corners, weights, inside


def bilinear(
    grid: NDArray[np.float32],
    corners: tuple[NDArray[np.intp], ...],
    weights: tuple[FloatArray, ...],
) -> FloatArray:
    """``grid`` (flattened) at the :func:`bilinear_corners`' positions, bilinearly."""
    flat = grid.reshape(-1)
    value: FloatArray = sum(w * flat[i] for w, i in zip(weights, corners, strict=True))  # type: ignore[assignment]
    return value
