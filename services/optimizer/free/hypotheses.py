"""Pose hypotheses from the target's boxes alone: RANSAC over minimal sets and their assignments.

Which object a detection is comes from its label: a scene's own detector names the object's
identity class (look-alikes share one), the general model names its shape. So each detection
``i`` has a set of compatible objects ``J_i``, a single one when its label is unique.

A minimal set is three detections and an assignment of distinct compatible objects to them;
OpenCV's AP3P (``cv2.solveP3P``, Ke & Roumeliotis 2017) gives up to four poses from the box
centres against the objects' centroids. Every pose is scored against all detections at once: the
objects' centroids are projected, each detection may pair with a compatible object whose
projected centroid lies within its gate (:func:`centre_gate`), and the one-to-one pairing is the
gated Hungarian assignment of :func:`~services.optimizer.matching.assign`. Poses are ranked by
their inliers, then by their summed gated cost, and the best distinct ones (more than
:data:`DISTINCT_POSITION` of the scene radius or :data:`DISTINCT_ROTATION_DEG` apart) are kept.

With at most :data:`MAX_MINIMAL_SOLVES` minimal sets in all, every one is solved (deterministic);
beyond it a seeded random sample of that many is.

A pose whose camera is below the ground (``z ≤ 0``) is dropped: the ground is opaque and the
renderer refuses such cameras. This removes the mirror twin that coplanar centroids (every
object's centre at about the same height) give P3P.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.optimizer.free.objects import SceneObjects
from services.optimizer.free.refine import Intrinsics
from services.optimizer.geometry import FloatArray
from services.optimizer.matching import assign

__all__ = [
    "DISTINCT_POSITION",
    "DISTINCT_ROTATION_DEG",
    "MAX_MINIMAL_SOLVES",
    "Hypothesis",
    "centre_gate",
    "compatibility",
    "distinct",
    "hypotheses",
    "pose_distance",
]

MAX_MINIMAL_SOLVES: Final = 1500
DISTINCT_POSITION: Final = 0.05
"""Two poses are distinct when their camera centres are this share of the scene radius apart…"""
DISTINCT_ROTATION_DEG: Final = 5.0
"""…or their orientations this many degrees apart."""
GATE_BOX_FRACTION: Final = 0.5
GATE_IMAGE_FRACTION: Final = 0.03


@dataclass(frozen=True)
class Hypothesis:
    """A pose (world-to-camera ``rvec``, ``tvec``) and the pairs it explains."""

    rvec: FloatArray
    tvec: FloatArray
    detections: NDArray[np.intp]
    objects: NDArray[np.intp]
    cost: float

    @property
    def inliers(self) -> int:
        return len(self.detections)

    def position(self) -> FloatArray:
        r, _ = cv2.Rodrigues(self.rvec)
        c: FloatArray = -np.asarray(r).T @ self.tvec
        return c


def compatibility(objects: SceneObjects, labels: tuple[str, ...]) -> NDArray[np.bool_]:
    """(D, M): may detection ``i`` be object ``j``? Its label is the object's identity class,
    its shape (the general model) or its name."""
    out = np.zeros((len(labels), len(objects)), dtype=np.bool_)
    for i, label in enumerate(labels):
        for j in range(len(objects)):
            out[i, j] = label in (objects.labels[j], objects.shapes[j], objects.names[j])
    return out


def centre_gate(boxes: ArrayLike, width: int, height: int) -> FloatArray:
    """(D,) how far (pixels) a projected centroid may lie from a box's centre to pair with it:
    half the box's diagonal, at least 3 % of the image's (a minimal set's pose, solved on
    uncorrected centres, is that rough)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    diag = np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    gate: FloatArray = np.maximum(
        GATE_BOX_FRACTION * diag, GATE_IMAGE_FRACTION * math.hypot(width, height)
    )
    return gate


def pose_distance(
    a: tuple[FloatArray, FloatArray], b: tuple[FloatArray, FloatArray]
) -> tuple[float, float]:
    """Camera-centre distance (scene units) and rotation angle (degrees) between poses given as
    world-to-camera ``(rvec, tvec)``."""
    ra, _ = cv2.Rodrigues(a[0])
    rb, _ = cv2.Rodrigues(b[0])
    ca, cb = -ra.T @ a[1], -rb.T @ b[1]
    cos = (np.trace(ra @ rb.T) - 1.0) / 2.0
    return float(np.linalg.norm(ca - cb)), math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def distinct(
    a: tuple[FloatArray, FloatArray], b: tuple[FloatArray, FloatArray], radius: float
) -> bool:
    """Whether two poses are distinct (module docstring)."""
    moved, turned = pose_distance(a, b)
    return moved > DISTINCT_POSITION * radius or turned > DISTINCT_ROTATION_DEG


def _minimal_sets(
    compatible: NDArray[np.bool_], rng: np.random.Generator
) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """(detections, objects) triples: all of them up to :data:`MAX_MINIMAL_SOLVES`, else a
    seeded sample of that many."""
    usable = [i for i in range(len(compatible)) if compatible[i].any()]
    candidates = [np.flatnonzero(row) for row in compatible]
    triples = list(itertools.combinations(usable, 3))
    counts = [math.prod(len(candidates[i]) for i in t) for t in triples]
    if sum(counts) <= MAX_MINIMAL_SOLVES:
        return [
            (tuple(t), objs)
            for t in triples
            for objs in itertools.product(*(candidates[i].tolist() for i in t))
            if len(set(objs)) == 3
        ]
    sets: list[tuple[tuple[int, ...], tuple[int, ...]]] = []
    for _ in range(MAX_MINIMAL_SOLVES):
        t = triples[int(rng.integers(len(triples)))]
        objs = tuple(int(rng.choice(candidates[i])) for i in t)
        if len(set(objs)) == 3:
            sets.append((t, objs))
    return sets


def _score(
    objects: SceneObjects,
    centres: FloatArray,
    gates: FloatArray,
    compatible: NDArray[np.bool_],
    rvec: FloatArray,
    tvec: FloatArray,
    intrinsics: Intrinsics,
) -> Hypothesis:
    rotation, _ = cv2.Rodrigues(rvec)
    cam = objects.centroids @ rotation.T + tvec
    with np.errstate(divide="ignore", invalid="ignore"):
        pix = cam[:, :2] / cam[:, 2:3] * (intrinsics.fx, intrinsics.fy)
    pix += (intrinsics.cx, intrinsics.cy)
    dist = np.linalg.norm(centres[:, np.newaxis, :] - pix[np.newaxis, :, :], axis=-1)
    cost = dist / gates[:, np.newaxis]
    cost[~compatible | (cam[:, 2] <= 0.0)[np.newaxis, :]] = np.inf
    pairs = assign(cost, 1.0)
    unpaired = len(centres) - len(pairs)
    return Hypothesis(
        rvec=rvec,
        tvec=tvec,
        detections=pairs.rows,
        objects=pairs.cols,
        cost=float(pairs.costs.sum()) + unpaired,
    )


def hypotheses(
    objects: SceneObjects,
    boxes: ArrayLike,
    compatible: NDArray[np.bool_],
    intrinsics: Intrinsics,
    width: int,
    height: int,
    *,
    keep: int = 8,
    seed: int = 0,
) -> list[Hypothesis]:
    """The best ``keep`` distinct pose hypotheses from the boxes' centres (module docstring),
    best first; empty when fewer than three detections have a compatible object."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    centres = (b[:, :2] + b[:, 2:]) / 2.0
    gates = centre_gate(b, width, height)
    k = intrinsics.matrix()
    scored: list[Hypothesis] = []
    for dets, objs in _minimal_sets(compatible, np.random.default_rng(seed)):
        count, rvecs, tvecs = cv2.solveP3P(
            objects.centroids[list(objs)],
            centres[list(dets)],
            k,
            None,
            flags=cv2.SOLVEPNP_AP3P,
        )
        for s in range(int(count)):
            r = np.asarray(rvecs[s], dtype=np.float64).reshape(3)
            t = np.asarray(tvecs[s], dtype=np.float64).reshape(3)
            rot, _ = cv2.Rodrigues(r)
            if not np.all(np.isfinite(t)) or (-rot.T @ t)[2] <= 0.0:
                continue
            scored.append(_score(objects, centres, gates, compatible, r, t, intrinsics))
    scored.sort(key=lambda h: (-h.inliers, h.cost))
    best: list[Hypothesis] = []
    for h in scored:
        if all(distinct((h.rvec, h.tvec), (o.rvec, o.tvec), objects.radius) for o in best):
            best.append(h)
            if len(best) == keep:
                break
    return best
