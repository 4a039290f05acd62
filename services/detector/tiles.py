"""Tiled detection of a large photo: small objects seen at the photo's own resolution.

The network sees every image shrunk into its fixed input (320 x 256 for the shipped model). A
drone's photo of several thousand pixels, taken high or through a wide lens, then shows its
objects a dozen input pixels across, smaller than any the models were trained on: they are
missed, or named wrongly. When the image is at least :data:`MIN_SHRINK` times the input along
both axes, it is also cut into an ``n x n`` grid of overlapping tiles (:func:`tile_grid`), each
letterboxed into the input on its own, so each object is seen ``n / (1 + OVERLAP)`` times
larger (1.6 times in the 2 x 2 grid), as SAHI (slicing-aided hyper inference) does.

Merging (:func:`merged`), by the size ``s`` of a box in the whole image's input (its longer side
times the whole image's letterbox gain) against :data:`SMALL_PX`, the smallest objects the
models are trained on:

* the whole image's pass is kept for what it sees large enough (``s ≥ SMALL_PX``): its boxes
  of large objects were the closer ones (a demo ball 44 input pixels across came 3-6 photo
  pixels off on a tile, where the ball was 70), and a tile's box as large
  (``s ≥ TILE_LARGE · SMALL_PX``) is dropped;
* a small box of the whole image's pass that lies whole inside a tile is dropped: that tile saw
  the object larger, and its name for it is the better informed one (the garden's model named
  its red ball, 15 input pixels wide, ``duck`` at 0.84 on the whole photo, ``red`` at 0.62 on a
  tile); one that no tile holds whole is kept;
* a tile's box that touches one of the tile's inner edges (an edge that is not the image's) may
  be a part of an object cut there, and is dropped; the tiles overlap by :data:`OVERLAP` of a
  tile, so an object narrower than that lies whole within some tile.

An object near ``SMALL_PX`` may come from both passes: NMS, as for one image, then keeps one.

SAHI (the ``sahi`` package) slices alike, but merges by NMS over the whole image's boxes and the
slices' together, which keeps the whole photo's confident wrong names, and its model wrappers
would bypass this service's batcher and admission: the grid and the merge are these few lines.

Measured by ``python -m benchmarks.tiled_detection`` (its docstring) and through the stack by
``cosmos bench --free --target-width 1280 --fov-range 0.55,1.8`` with ``COSMOS_DETECTOR_TILES``
0 and 2: see ``docs/EVALUATION.md``.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.detector.postprocess import Candidates

__all__ = [
    "MIN_SHRINK",
    "OVERLAP",
    "SMALL_PX",
    "TILE_LARGE",
    "Tile",
    "merged",
    "tile_grid",
    "wants_tiles",
]

MIN_SHRINK: Final = 2.0
"""Tiles are cut only from an image at least this many times the network's input along both
axes: a tile of the 2 x 2 grid, ``(1 + OVERLAP) / 2`` of it, is then still 1.25 times the input
or more, never enlarged (finer grids enlarge the tiles of the smallest such images)."""
OVERLAP: Final = 0.25
"""Each tile is ``(1 + OVERLAP) / n`` of the image along each axis."""
SMALL_PX: Final = 32.0
"""Input pixels (the box's longer side in the whole image's input) under which an object is
small: a tenth of the shipped 320-pixel input, about the smallest object of the models'
training views (a demo ball at 1.6 scene radii through a lens 30 % wider than the scene
camera's is ~22)."""
TILE_LARGE: Final = 1.25
"""A tile's box at least this times :data:`SMALL_PX` (in the whole image's input) is left to
the whole image's pass; between the two, both passes may keep it and NMS decides."""
EDGE_PX: Final = 1.0
"""A box within this many image pixels of a tile's inner edge touches it."""

Tile = tuple[int, int, int, int]
"""``x0, y0, x1, y1`` in image pixels (pixel edges)."""


def wants_tiles(image_size: tuple[int, int], input_size: tuple[int, int], n: int) -> bool:
    """Whether an image of ``image_size`` (w, h) is also detected in ``n x n`` tiles for a
    network input of ``input_size``: ``n ≥ 2`` and the image at least :data:`MIN_SHRINK` times
    the input along both axes."""
    (w, h), (in_w, in_h) = image_size, input_size
    return n >= 2 and w >= MIN_SHRINK * in_w and h >= MIN_SHRINK * in_h


def tile_grid(image_size: tuple[int, int], n: int) -> list[Tile]:
    """``n x n`` tiles of ``(1 + OVERLAP) / n`` of the image each, spread evenly from edge to
    edge, row by row."""
    w, h = image_size
    tw, th = min(w, round(w * (1.0 + OVERLAP) / n)), min(h, round(h * (1.0 + OVERLAP) / n))
    xs = np.linspace(0, w - tw, n).round().astype(int)
    ys = np.linspace(0, h - th, n).round().astype(int)
    return [(int(x), int(y), int(x) + tw, int(y) + th) for y in ys for x in xs]


def _inside(
    boxes: NDArray[np.float64], tile: Tile, image_size: tuple[int, int]
) -> NDArray[np.bool_]:
    """Which boxes lie whole inside ``tile``, off its inner edges (an edge on the image's own
    border is no cut)."""
    x0, y0, x1, y1 = tile
    w, h = image_size
    return (
        ((boxes[:, 0] > x0 + EDGE_PX) | (x0 == 0))
        & ((boxes[:, 1] > y0 + EDGE_PX) | (y0 == 0))
        & ((boxes[:, 2] < x1 - EDGE_PX) | (x1 == w))
        & ((boxes[:, 3] < y1 - EDGE_PX) | (y1 == h))
    )


def _size(boxes: NDArray[np.float64], gain: float) -> NDArray[np.float64]:
    """Each box's longer side in the whole image's input pixels."""
    sides: NDArray[np.float64] = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    return sides * gain


def merged(
    whole: Candidates,
    tiled: list[tuple[Tile, Candidates]],
    image_size: tuple[int, int],
    gain: float,
) -> Candidates:
    """The whole image's candidates and its tiles' (boxes in image pixels) as one set, best
    score first (module docstring), for NMS; ``gain`` is the whole image's input pixels per
    image pixel."""
    held = np.zeros(len(whole.boxes), dtype=np.bool_)
    for tile, _ in tiled:
        held |= _inside(whole.boxes, tile, image_size)
    keep = ~held | (_size(whole.boxes, gain) >= SMALL_PX)
    parts = [whole.take(np.flatnonzero(keep))]
    for tile, found in tiled:
        keep = _inside(found.boxes, tile, image_size)
        keep &= _size(found.boxes, gain) < TILE_LARGE * SMALL_PX
        parts.append(found.take(np.flatnonzero(keep)))
    joined = Candidates(
        np.concatenate([p.boxes for p in parts]).reshape(-1, 4),
        np.concatenate([p.scores for p in parts]),
        np.concatenate([p.class_ids for p in parts]),
    )
    return joined.take(np.argsort(-joined.scores, kind="stable"))
