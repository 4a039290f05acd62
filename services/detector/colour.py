"""The colour of a detected object: the mean sRGB of its own pixels inside its box, ground excluded.

The ground around an object is sampled from a ring just outside its box; a pixel inside the box
belongs to the object when its colour is far (CIELAB ΔE) from every colour of that ring. This
works on a plain, shaded or textured ground alike, because the ring holds the ground's own
variety (tiles, grout, the object's shadow where it reaches past the box). Specks are dropped, a
grey object's parts are joined (its shading may cross the ground's grey), the rim (anti-aliased
blends of object and ground) is eroded, and pixels of a clearly different hue (an occluder, a
leaked shadow) are dropped before averaging.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["measure_colour"]

_SAMPLE_SIDE = 64  # the box is sampled on a grid of at most this many pixels per side
_PALETTE = 256  # ground colours kept from the ring
_HUE_TOLERANCE_DEG = 35.0
_CHROMATIC = 15.0  # Lab chroma above which an object counts as coloured (not grey)
_MIN_PART = 0.2  # blobs at least this fraction of the largest one are parts of the object
# Palette colours x samples per matrix product: OpenBLAS runs products this small (M N K <= 2^18,
# K = 4) on the calling thread, where bigger ones wake its thread pool for microseconds of work.
_PRODUCT_CELLS = 2**16


def _lab(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """CIELAB (L in 0-100, a and b roughly -128..127) of 8-bit sRGB pixels ``(N, 3)``, as
    ``(N, 3)``."""
    flat = rgb.reshape(1, -1, 3).astype(np.float32)
    flat /= np.float32(255.0)
    return np.asarray(cv2.cvtColor(flat, cv2.COLOR_RGB2Lab), dtype=np.float32).reshape(-1, 3)


def _median(values: NDArray[np.float32]) -> float:
    """``np.median`` of a non-empty float32 vector, bit for bit, without its overhead."""
    half = values.shape[0] // 2
    if values.shape[0] % 2:
        return float(np.partition(values, half)[half])
    middle = np.partition(values, (half - 1, half))
    return float((middle[half - 1] + middle[half]) / np.float32(2.0))


def _spread(count: int) -> NDArray[np.intp]:
    """Indices of at most ``_PALETTE`` of ``count`` items, evenly spread over them."""
    if count <= _PALETTE:
        return np.arange(count)
    return np.linspace(0, count - 1, _PALETTE).astype(np.intp)


def _pixel_range(lo: float, hi: float, size: int) -> tuple[int, int]:
    """Pixels whose centres ``i + 0.5`` lie in ``[lo, hi]``, as a half-open range within
    ``[0, size)``."""
    start = max(0, math.ceil(lo - 0.5))
    stop = min(size, math.floor(hi - 0.5) + 1)
    return start, max(start, stop)


def _ring(
    rgb: NDArray[np.uint8], rows: tuple[int, int], cols: tuple[int, int], gap: int, width: int
) -> tuple[NDArray[np.uint8], int]:
    """Pixels between the box grown by ``gap`` and by ``gap + width``, clipped: at most
    ``_PALETTE`` of them ``(K, 3)`` spread evenly in raster order (:func:`_spread`), and how
    many there are in all."""
    height, full_width = rgb.shape[:2]
    r0, r1 = max(0, rows[0] - gap - width), min(height, rows[1] + gap + width)
    c0, c1 = max(0, cols[0] - gap - width), min(full_width, cols[1] + gap + width)
    outer = np.ones((r1 - r0, c1 - c0), dtype=bool)
    ir0, ir1 = max(r0, rows[0] - gap), min(r1, rows[1] + gap)
    ic0, ic1 = max(c0, cols[0] - gap), min(c1, cols[1] + gap)
    outer[ir0 - r0 : ir1 - r0, ic0 - c0 : ic1 - c0] = False
    ring = np.flatnonzero(outer)
    kept = ring[_spread(ring.size)]
    sample: NDArray[np.uint8] = rgb[r0 + kept // (c1 - c0), c0 + kept % (c1 - c0)]
    return sample, ring.size


def _far_from(
    points: NDArray[np.float32], palette: NDArray[np.float32], delta_e: float
) -> NDArray[np.bool_]:
    """Which points ``(N, 3)`` are farther than ``delta_e`` from every palette colour ``(M, 3)``.

    Decides ``min_g ||p - g||^2 > delta_e^2`` exactly as the float32 brute force
    ``cv2.batchDistance(points, palette, NORM_L2SQR, K=1)`` does, at a fraction of its cost:

    1. a point more than ``|delta_e|`` (plus a rounding margin) outside the palette's bounding
       box in some coordinate is far from all of it;
    2. the others get ``d^2 = |g|^2 - 2 g.p + |p|^2`` from float32 matrix products (one augmented
       product ``[-2g, |g|^2] [p, 1]^T`` per block of points), minimised over the palette;
    3. the few whose ``d^2`` lies within the products' rounding error of the limit are decided
       again by ``cv2.batchDistance`` itself.
    """
    limit = np.float32(delta_e**2)
    reach = abs(delta_e) + 1e-3 * (1.0 + abs(delta_e))  # far beyond float32 rounding of |p - g|
    columns = palette.T.copy()  # numpy reduces a contiguous row much faster than a column
    low, high = columns.min(axis=1) - reach, columns.max(axis=1) + reach
    channels = points.T
    inside = (channels[0] >= low[0]) & (channels[0] <= high[0])
    for c in (1, 2):
        inside &= (channels[c] >= low[c]) & (channels[c] <= high[c])
    near = np.flatnonzero(inside)
    far = np.ones(points.shape[0], dtype=bool)
    if near.size == 0:
        return far
    lhs = np.empty((palette.shape[0], 4), dtype=np.float32)
    lhs[:, :3] = -2.0 * palette
    lhs[:, 3] = np.einsum("ij,ij->i", palette, palette)
    rhs = np.empty((4, near.size), dtype=np.float32)
    rhs[:3] = points.take(near, axis=0).T
    rhs[3] = 1.0
    squares = np.einsum("ij,ij->j", rhs[:3], rhs[:3])
    nearest = np.empty(near.size, dtype=np.float32)
    block = max(1, _PRODUCT_CELLS // palette.shape[0])
    for start in range(0, near.size, block):
        stop = start + block
        np.min(lhs @ rhs[:, start:stop], axis=0, out=nearest[start:stop])
    nearest += squares
    # float32 rounding of the three terms (each at most |p|^2 + |g|^2), with a wide margin
    tolerance = 1e-5 * (float(squares.max()) + float(lhs[:, 3].max()) + float(limit)) + 1e-3
    unsure = np.flatnonzero(np.abs(nearest - limit) <= tolerance)
    if unsure.size:
        exact, _ = cv2.batchDistance(
            points[near[unsure]], palette, cv2.CV_32F, normType=cv2.NORM_L2SQR, K=1
        )
        nearest[unsure] = exact.reshape(-1)
    far[near] = nearest > limit
    return far


def _hue_consistent(
    a: NDArray[np.float32], b: NDArray[np.float32], chroma: NDArray[np.float32]
) -> NDArray[np.bool_]:
    """Which of the pixels with Lab ``a``, ``b`` and chroma ``hypot(a, b)`` share the blob's
    dominant hue.

    A coloured blob (median chroma above ``_CHROMATIC``) keeps pixels within
    ``_HUE_TOLERANCE_DEG`` of its chroma-weighted mean hue and with at least a quarter of its
    median chroma (shading darkens a colour but keeps its hue); a grey blob keeps its
    near-grey pixels. A pixel's hue is within tolerance ``t`` of the mean hue ``h`` when
    ``a cos h + b sin h = chroma cos(gap) >= chroma cos t``.
    """
    median = _median(chroma)
    if median <= _CHROMATIC:
        keep: NDArray[np.bool_] = chroma <= max(2.0 * median, _CHROMATIC + 5.0)
        return keep
    mean_hue = math.atan2(float(b.sum()), float(a.sum()))  # chroma-weighted direction
    along = a * math.cos(mean_hue) + b * math.sin(mean_hue)
    keep = along >= chroma * math.cos(math.radians(_HUE_TOLERANCE_DEG))
    keep &= chroma >= 0.25 * median
    return keep


def measure_colour(
    rgb: NDArray[np.uint8],
    box: tuple[float, float, float, float],
    *,
    delta_e: float = 12.0,
    min_fraction: float = 0.02,
) -> tuple[float, float, float] | None:
    """The mean sRGB colour (0-255 per channel) of the object inside ``box``.

    Parameters
    ----------
    rgb
        The whole image, ``(H, W, 3)`` 8-bit sRGB.
    box
        ``x1, y1, x2, y2`` in pixels (edges); the pixels whose centres lie inside are examined.
    delta_e
        A pixel is the object's when its CIELAB distance to every sampled ground colour exceeds
        this (ΔE*ab; about 2.3 is a just-noticeable difference).
    min_fraction
        The fewest object pixels, as a fraction of the box, for a measurement (at least 6).

    Returns
    -------
    The mean (r, g, b) of the object's pixels, or None when the box is (nearly) empty, there
    is no ground around it to compare with, or too few pixels stand out from the ground.

    Notes
    -----
    Steps, on a grid of at most 64 x 64 samples of the box:

    1. ground palette G: up to 256 pixels of the ring between the box grown by
       ``gap = max(1, 0.05 s)`` and by ``gap + max(2, 0.1 s)`` pixels (s the box's longer side);
       if the box leaves no ring (it fills the image), the box's own one-pixel border;
    2. object mask: ``min_{g in G} ||Lab(p) - Lab(g)|| > delta_e``;
    3. its 8-connected components of at least a fifth of the largest one's area; for a grey
       object (median Lab chroma <= 15) their convex hull, since shading through the ground's
       grey splits it into a lit and a dark part;
    4. erosion by one sample (3 x 3) when that leaves enough, which drops the blended rim;
    5. hue consistency (:func:`_hue_consistent`), then the mean of the remaining pixels' sRGB.
    """
    height, width = rgb.shape[:2]
    cols = _pixel_range(box[0], box[2], width)
    rows = _pixel_range(box[1], box[3], height)
    box_w, box_h = cols[1] - cols[0], rows[1] - rows[0]
    if box_w < 3 or box_h < 3:
        return None
    side = max(box_w, box_h)
    step = max(1, math.ceil(side / _SAMPLE_SIDE))
    crop = np.ascontiguousarray(rgb[rows[0] : rows[1] : step, cols[0] : cols[1] : step])
    samples = crop.reshape(-1, 3)
    min_pixels = max(6, math.ceil(min_fraction * crop.shape[0] * crop.shape[1]))

    ground, ring_size = _ring(
        rgb, rows, cols, max(1, round(0.05 * side)), max(2, round(0.1 * side))
    )
    if ring_size < 8:
        inside = rgb[rows[0] : rows[1], cols[0] : cols[1]]
        ground = np.concatenate([inside[0], inside[-1], inside[:, 0], inside[:, -1]])
        ground = ground[_spread(ground.shape[0])]

    points = _lab(samples)
    far = _far_from(points, _lab(ground), delta_e)
    mask = far.view(np.uint8).reshape(crop.shape[:2])

    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count < 2:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    big = 1 + np.flatnonzero(areas >= max(min_pixels, _MIN_PART * int(areas.max())))
    if big.size == 0:
        return None
    is_big = np.zeros(count, dtype=np.uint8)
    is_big[big] = 1
    blob = is_big[labels]
    a, b = points[:, 1], points[:, 2]
    chroma = np.hypot(a, b)
    if _median(chroma[blob.reshape(-1).view(bool)]) <= _CHROMATIC:
        # A grey object shaded through the ground's own grey splits into a lit and a dark
        # part; the object is what lies between them too.
        hull = cv2.convexHull(cv2.findNonZero(blob))
        cv2.fillConvexPoly(blob, hull, 1)
    eroded = cv2.erode(blob, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    chosen = np.flatnonzero(eroded if cv2.countNonZero(eroded) >= min_pixels else blob)
    if chosen.size < min_pixels:
        return None
    kept = chosen[_hue_consistent(a[chosen], b[chosen], chroma[chosen])]
    if kept.size < min_pixels:
        return None
    weights = np.zeros(samples.shape[0], dtype=np.int64)
    weights[kept] = 1
    # exact integer sums, so the mean is the float64 mean of the pixels, bit for bit
    mean = (weights @ samples.astype(np.int64)) / kept.size
    return (round(float(mean[0]), 1), round(float(mean[1]), 1), round(float(mean[2]), 1))
