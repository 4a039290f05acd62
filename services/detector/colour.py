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


def _lab(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """CIELAB (L in 0-100, a and b roughly -128..127) of 8-bit sRGB pixels ``(..., 3)``."""
    flat = np.ascontiguousarray(rgb.reshape(1, -1, 3), dtype=np.float32) / np.float32(255.0)
    return np.asarray(cv2.cvtColor(flat, cv2.COLOR_RGB2Lab), dtype=np.float32).reshape(rgb.shape)


def _pixel_range(lo: float, hi: float, size: int) -> tuple[int, int]:
    """Pixels whose centres ``i + 0.5`` lie in ``[lo, hi]``, as a half-open range within
    ``[0, size)``."""
    start = max(0, math.ceil(lo - 0.5))
    stop = min(size, math.floor(hi - 0.5) + 1)
    return start, max(start, stop)


def _ring(
    rgb: NDArray[np.uint8], rows: tuple[int, int], cols: tuple[int, int], gap: int, width: int
) -> NDArray[np.uint8]:
    """Pixels ``(K, 3)`` between the box grown by ``gap`` and by ``gap + width``, clipped."""
    height, full_width = rgb.shape[:2]
    r0, r1 = max(0, rows[0] - gap - width), min(height, rows[1] + gap + width)
    c0, c1 = max(0, cols[0] - gap - width), min(full_width, cols[1] + gap + width)
    outer = np.ones((r1 - r0, c1 - c0), dtype=bool)
    ir0, ir1 = max(r0, rows[0] - gap), min(r1, rows[1] + gap)
    ic0, ic1 = max(c0, cols[0] - gap), min(c1, cols[1] + gap)
    outer[ir0 - r0 : ir1 - r0, ic0 - c0 : ic1 - c0] = False
    ring: NDArray[np.uint8] = rgb[r0:r1, c0:c1][outer]
    return ring


def _median_chroma(lab: NDArray[np.float32]) -> float:
    return float(np.median(np.hypot(lab[:, 1], lab[:, 2]))) if lab.shape[0] else 0.0


def _hue_consistent(lab: NDArray[np.float32]) -> NDArray[np.bool_]:
    """Which of the pixels ``(K, 3)`` (Lab) share the blob's dominant hue.

    A coloured blob (median chroma above ``_CHROMATIC``) keeps pixels within
    ``_HUE_TOLERANCE_DEG`` of its chroma-weighted mean hue and with at least a quarter of its
    median chroma (shading darkens a colour but keeps its hue); a grey blob keeps its
    near-grey pixels.
    """
    a, b = lab[:, 1], lab[:, 2]
    chroma = np.hypot(a, b)
    median = _median_chroma(lab)
    if median <= _CHROMATIC:
        keep: NDArray[np.bool_] = chroma <= max(2.0 * median, _CHROMATIC + 5.0)
        return keep
    mean_hue = math.atan2(float(b.sum()), float(a.sum()))  # chroma-weighted direction
    gap = np.abs(np.angle(np.exp(1j * (np.arctan2(b, a) - mean_hue))))
    keep = (gap <= math.radians(_HUE_TOLERANCE_DEG)) & (chroma >= 0.25 * median)
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
    crop = rgb[rows[0] : rows[1] : step, cols[0] : cols[1] : step]
    min_pixels = max(6, math.ceil(min_fraction * crop.shape[0] * crop.shape[1]))

    ground = _ring(rgb, rows, cols, max(1, round(0.05 * side)), max(2, round(0.1 * side)))
    if ground.shape[0] < 8:
        inside = rgb[rows[0] : rows[1], cols[0] : cols[1]]
        ground = np.concatenate([inside[0], inside[-1], inside[:, 0], inside[:, -1]])
    if ground.shape[0] > _PALETTE:
        ground = ground[np.linspace(0, ground.shape[0] - 1, _PALETTE).astype(np.intp)]

    points = _lab(crop).reshape(-1, 3)
    palette = _lab(ground).reshape(-1, 3)
    # squared distance of each sample to its nearest ground colour (OpenCV's brute-force search)
    nearest, _ = cv2.batchDistance(points, palette, cv2.CV_32F, normType=cv2.NORM_L2SQR, K=1)
    mask = (nearest.reshape(crop.shape[:2]) > delta_e**2).astype(np.uint8)

    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count < 2:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    big = 1 + np.flatnonzero(areas >= max(min_pixels, _MIN_PART * int(areas.max())))
    if big.size == 0:
        return None
    blob = np.isin(labels, big).astype(np.uint8)
    if _median_chroma(points[blob.reshape(-1).astype(bool)]) <= _CHROMATIC:
        # A grey object shaded through the ground's own grey splits into a lit and a dark
        # part; the object is what lies between them too.
        hull = cv2.convexHull(cv2.findNonZero(blob))
        cv2.fillConvexPoly(blob, hull, 1)
    eroded = cv2.erode(blob, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    chosen = (eroded if int(eroded.sum()) >= min_pixels else blob).astype(bool).reshape(-1)
    if int(chosen.sum()) < min_pixels:
        return None
    keep = _hue_consistent(points[chosen])
    if int(keep.sum()) < min_pixels:
        return None
    mean = crop.reshape(-1, 3)[chosen][keep].astype(np.float64).mean(axis=0)
    return (round(float(mean[0]), 1), round(float(mean[1]), 1), round(float(mean[2]), 1))
