"""Which minimal sets (three detections, three objects) the pose hypotheses solve
(:mod:`.hypotheses`).

Up to :data:`MAX_MINIMAL_SOLVES` sets in all, every one. Beyond it, the detection triples are
taken in order of confidence (most confident first, ordered by their least confident member,
then by the sum of ranks, so that one bad box spoils few of them), and for each:

* with the general model's labels (every object fits every detection), every assignment,
  matching shapes first, up to :data:`MAX_GENERAL_SOLVES`, from the detections that are not a
  second box on a more confident one's object (:func:`seeds_of`);
* with a scene's own detector and many look-alikes, the :data:`CONSISTENT_PER_TRIPLE`
  assignments whose triangle is most like the objects' own (:class:`Spans`: a box's size puts
  its object at a depth, so a wrong assignment's triangle has the wrong size or shape).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.optimizer.free.objects import SceneObjects
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.tolerances import box_diagonals
from services.optimizer.geometry import FloatArray
from services.optimizer.observations import DUPLICATE_IOU, box_overlaps

__all__ = [
    "CONSISTENT_PER_TRIPLE",
    "MAX_GENERAL_SOLVES",
    "MAX_MINIMAL_SOLVES",
    "Spans",
    "minimal_sets",
    "seeds_of",
]

MAX_MINIMAL_SOLVES: Final = 1500
CONSISTENT_PER_TRIPLE: Final = 30
"""Assignments solved per detection triple when look-alikes are too many to solve them all."""
MAX_GENERAL_SOLVES: Final = 6000
"""The cap with the general model's labels (every object fits every detection)."""


def seeds_of(boxes: FloatArray, order: NDArray[np.intp], usable: list[int]) -> list[int]:
    """The usable detections in ``order`` (most confident first), less the second boxes on a
    kept one's object (IoU ≥ ``DUPLICATE_IOU``)."""
    iou = box_overlaps(boxes)[0]
    kept: list[int] = []
    for i in (int(i) for i in order if int(i) in usable):
        if not np.any(iou[i, kept] >= DUPLICATE_IOU):
            kept.append(i)
    return kept


def minimal_sets(
    costs: FloatArray,
    boxes: FloatArray,
    order: NDArray[np.intp],
    rng: np.random.Generator,
    general: bool,
    camera: tuple[SceneObjects, Intrinsics],
) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """(detections, objects) triples: all of them up to :data:`MAX_MINIMAL_SOLVES`, else the
    most consistent assignments of the most confident detection triples (a scene's own
    detector: :func:`_consistent_sets`), or every assignment of them (the general model), up to
    that many (module docstring); ``camera`` (the objects and the intrinsics) places the
    look-alikes' triangles (:class:`Spans`)."""
    compatible = np.isfinite(costs)
    usable = [i for i in range(len(compatible)) if compatible[i].any()]
    candidates = [np.flatnonzero(row) for row in compatible]
    triples = list(itertools.combinations(usable, 3))
    counts = [math.prod(len(candidates[i]) for i in t) for t in triples]
    cap = MAX_GENERAL_SOLVES if general else MAX_MINIMAL_SOLVES
    if sum(counts) <= cap:
        return [
            (tuple(t), objs)
            for t in triples
            for objs in itertools.product(*(candidates[i].tolist() for i in t))
            if len(set(objs)) == 3
        ]
    if not general:
        ordered = [int(i) for i in order if int(i) in usable]
        objects, k = camera
        return _consistent_sets(candidates, ordered, Spans.of(objects, boxes, k))
    seeds = seeds_of(boxes, order, usable)
    ranked = sorted(itertools.combinations(range(len(seeds)), 3), key=lambda t: (t[2], sum(t)))
    sets: list[tuple[tuple[int, ...], tuple[int, ...]]] = []
    for ranks in ranked:
        dets = tuple(seeds[r] for r in ranks)
        objs = np.array(
            [a for a in itertools.product(*(candidates[i] for i in dets)) if len(set(a)) == 3],
            dtype=np.intp,
        ).reshape(-1, 3)
        objs = objs[rng.permutation(len(objs))]
        price = sum(costs[d, objs[:, n]] for n, d in enumerate(dets))
        objs = objs[np.argsort(price, kind="stable")][: cap - len(sets)]
        sets += [(dets, (int(a), int(b), int(c))) for a, b, c in objs]
        if len(sets) >= cap:
            break
    return sets


@dataclass(frozen=True)
class Spans:
    """Where each detection's object would stand in the camera frame, ``points`` (D, M, 3),
    were it object ``j``: on its box centre's ray, at the depth ``z = f s_j / d_i`` at which
    the object's size ``s_j`` (its points' bounding-box diagonal) spans the box's diagonal
    ``d_i``; and the objects' world centroids (M, 3)."""

    points: FloatArray
    centroids: FloatArray

    @classmethod
    def of(cls, objects: SceneObjects, boxes: FloatArray, k: Intrinsics) -> Spans:
        lo = np.minimum.reduceat(objects.points, objects.starts)
        hi = np.maximum.reduceat(objects.points, objects.starts)
        size = np.linalg.norm(hi - lo, axis=1)
        spanned = np.maximum(box_diagonals(boxes), 1.0)
        centres = (boxes[:, :2] + boxes[:, 2:]) / 2.0
        rays = np.column_stack(
            [(centres[:, 0] - k.cx) / k.fx, (centres[:, 1] - k.cy) / k.fy, np.ones(len(boxes))]
        )
        depth = k.fx * size[np.newaxis, :] / spanned[:, np.newaxis]
        return cls(depth[..., np.newaxis] * rays[:, np.newaxis, :], objects.centroids)

    def mismatch(self, dets: tuple[int, ...], objs: NDArray[np.intp]) -> FloatArray:
        """(A,) how far the triangle of detections ``dets`` as objects ``objs`` (A, 3) is from
        the objects' own: the largest ``|log(l_camera / l_world)|`` over its three sides."""
        worst = np.zeros(len(objs))
        for u, v in ((0, 1), (1, 2), (0, 2)):
            here = self.points[dets[u], objs[:, u]] - self.points[dets[v], objs[:, v]]
            there = self.centroids[objs[:, u]] - self.centroids[objs[:, v]]
            with np.errstate(divide="ignore"):
                ratio = np.log(np.linalg.norm(here, axis=1) / np.linalg.norm(there, axis=1))
            worst = np.maximum(worst, np.abs(ratio))
        return worst


def _assignments(candidates: list[NDArray[np.intp]], dets: tuple[int, ...]) -> NDArray[np.intp]:
    """(A, 3) every assignment of distinct compatible objects to the three ``dets``."""
    grids = np.meshgrid(*(candidates[i] for i in dets), indexing="ij")
    a = np.stack([g.ravel() for g in grids], axis=1).astype(np.intp).reshape(-1, 3)
    distinct: NDArray[np.intp] = a[
        (a[:, 0] != a[:, 1]) & (a[:, 1] != a[:, 2]) & (a[:, 0] != a[:, 2])
    ]
    return distinct


def _consistent_sets(
    candidates: list[NDArray[np.intp]], ordered: list[int], spans: Spans
) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Look-alikes too many to solve every set: the detection triples in order of confidence
    (as the general model's), each with its :data:`CONSISTENT_PER_TRIPLE` assignments whose
    triangle is most like the objects' own (:meth:`Spans.mismatch`: box sizes give depths,
    so a wrong assignment's triangle is the wrong size or shape), up to
    :data:`MAX_MINIMAL_SOLVES` sets. Before, as many sets were drawn at random; ``python -m
    benchmarks.lookalikes`` (identical cubes only, 0.7 px of box noise, 20 views a count, one
    run each way) found 19, 20 and 19 of 20 for 8, 12 and 20 look-alikes, against 19, 15 and
    9 drawn at random, none wrong either way; the median solve took 92-260 ms against
    154-212 ms."""
    ranked = sorted(itertools.combinations(range(len(ordered)), 3), key=lambda t: (t[2], sum(t)))
    sets: list[tuple[tuple[int, ...], tuple[int, ...]]] = []
    for ranks in ranked:
        dets = tuple(ordered[r] for r in ranks)
        objs = _assignments(candidates, dets)
        best = np.argsort(spans.mismatch(dets, objs), kind="stable")
        keep = objs[best[: min(CONSISTENT_PER_TRIPLE, MAX_MINIMAL_SOLVES - len(sets))]]
        sets += [(dets, (int(a), int(b), int(c))) for a, b, c in keep]
        if len(sets) >= MAX_MINIMAL_SOLVES:
            break
    return sets
