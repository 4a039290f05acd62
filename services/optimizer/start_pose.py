"""The grid pose a hemisphere search should render first, from the target's detections alone.

A scene file says where every object stands, so before anything is rendered the target's boxes
already say where the camera was: the scene's objects (:func:`~.free.objects.scene_objects`, as
point sets whose projected bounding box is the object's image box) are projected into every pose
of the scene's grid, with the scene camera looking at the centre, and each pose is scored against
the target's boxes. A search then takes its first view at the best pose and usually ends there.

Predicted boxes
---------------
At grid pose ``g`` with world-to-camera ``R_g`` and centre ``c_g``, object ``k``'s box is the
min and max over its points ``X`` of ``u = f x_c / z_c + c_x``, ``v = f y_c / z_c + c_y``,
``x_c = R_g (X − c_g)`` (:class:`GridViews`, every pose at once, computed once per scene and
grid and kept in :class:`GridViewCache`). Boxes are clipped to the image; an object is
*expected* when at least 30 % of its box is inside and both its sides are at least 2 px.
Occlusion is not modelled: an object hidden in the target costs the same at every pose that
expects it.

Score of a pose
---------------
As the reprojection strategy's (:mod:`.reprojection`), with the scene's exact boxes in place of
a map: a target detection ``j`` and an object ``k`` with a box in the image cost

.. math:: c_{jk} = \\frac{\\lVert B_j − \\hat B_k \\rVert^2}{4 s^2} + m_{jk},

the mean squared box-edge difference over ``s²`` (``s`` = :data:`~.reprojection.SCALE_PX`), and
the pose's score is the gated Hungarian optimum

.. math:: S = \\sum_{\\text{pairs}} \\min(c_{jk}, τ^2) + τ^2 \\, (\\#\\text{unpaired targets})
              + λ τ^2 \\, (\\#\\text{unpaired expected objects}).

Labels decide which pairs exist: with the scene's own detector (``object_classes`` given) a
label is an identity class and pairs only with its objects (look-alikes share one, geometry
tells them apart); with the general detector a label is a shape class, which may be wrong, so
a pair of another shape costs ``m`` = :data:`SHAPE_MISMATCH_COST` more. Every pose gets a cheap
score first (each detection's best partner, not one-to-one, which is never more than the exact
score); the :data:`NEAR_CANDIDATES` best are scored exactly.

Status
------
``ambiguous``
    A pose more than 1.5 grid steps (and :data:`MIN_RIVAL_DEG`) from the best scores within
    ``ratio · S_best +`` :data:`AMBIGUITY_MARGIN` (the reprojection strategy's test, ``ratio``
    its default 1.25):
    every distant pose whose cheap score is that low is scored exactly, so none is missed. Also
    a best pose that pairs a single detection.
``failed``
    The best pose pairs fewer than half of the target's detections: the scene's layout does not
    explain the target.
``found``
    Otherwise. A target between grid poses gets the grid pose whose view is likest; the search's
    strategy then finishes from there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.caches import LruFront, SharedLru, array_nbytes
from services.common.contracts.start_pose import StartStatus
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer.free.objects import NEAR_DEPTH, SceneObjects
from services.optimizer.geometry import FloatArray, PinholeCameras
from services.optimizer.matching import Assignment, assign
from services.optimizer.observations import Observation
from services.optimizer.proxies import clip_boxes
from services.optimizer.reprojection import GATE, MISSING_WEIGHT, SCALE_PX

__all__ = [
    "AMBIGUITY_MARGIN",
    "AMBIGUITY_RATIO",
    "NEAR_CANDIDATES",
    "SHAPE_MISMATCH_COST",
    "GridViewCache",
    "GridViews",
    "StartPrediction",
    "predict_start",
]

NEAR_CANDIDATES: Final = 8
MAX_RIVALS: Final = 16
"""Distant poses scored exactly at most (past a few the answer is ambiguous anyway)."""
AMBIGUITY_RATIO: Final = 1.25
AMBIGUITY_MARGIN: Final = 1.0
"""Score units: one object off by :data:`~.reprojection.SCALE_PX` pixels."""
SHAPE_MISMATCH_COST: Final = 4.0
"""Cost of pairing a general-detector box with an object of another shape: as if its edges were
off by 2 s = 8 px."""
MIN_RIVAL_DEG: Final = 10.0
"""A rival pose is at least this far from the best (and 1.5 grid steps): on a fine grid the
poses a few degrees off look alike without making the layout ambiguous (the search's strategy
refines from the start)."""
MIN_EXPECTED_INSIDE: Final = 0.3
MIN_SIDE_PX: Final = 2.0
_POINTS_PER_CHUNK: Final = 250_000
_COSTS_PER_CHUNK: Final = 4_000_000
MAX_ALTERNATIVES: Final = 5


@dataclass(frozen=True, eq=False)
class GridViews:
    """A scene's objects seen from every grid pose (flat order).

    Attributes
    ----------
    boxes : (N, M, 4) clipped image boxes, camera pixels; NaN where an object is behind the
        camera or out of the image.
    expected : (N, M) whether each pose should see each object (module docstring).
    labels, shapes : each object's identity class label and shape.
    directions : (N, 3) the poses' unit view directions (camera centres on the unit sphere).
    """

    boxes: FloatArray
    expected: NDArray[np.bool_]
    labels: tuple[str, ...]
    shapes: tuple[str, ...]
    directions: FloatArray

    @classmethod
    def of(cls, objects: SceneObjects, grid: HemisphereGrid, camera: CameraSpec) -> GridViews:
        """Project ``objects`` into every pose of ``grid`` (module docstring), in chunks of
        poses so that at most :data:`_POINTS_PER_CHUNK` projected points are held at once."""
        cameras = PinholeCameras.at(grid.theta_deg, grid.phi_deg, camera)
        n, m = len(cameras), len(objects)
        boxes = np.full((n, m, 4), np.nan)
        if m:
            chunk = max(1, _POINTS_PER_CHUNK // max(len(objects.points), 1))
            for lo in range(0, n, chunk):
                boxes[lo : lo + chunk] = _project(cameras, objects, lo, min(n, lo + chunk))
        clipped, inside = clip_boxes(boxes, camera.width, camera.height)
        expected = (
            (inside >= MIN_EXPECTED_INSIDE)
            & (clipped[..., 2] - clipped[..., 0] >= MIN_SIDE_PX)
            & (clipped[..., 3] - clipped[..., 1] >= MIN_SIDE_PX)
        )
        for array in (clipped, expected):
            array.flags.writeable = False
        return cls(
            boxes=clipped,
            expected=expected,
            labels=objects.labels,
            shapes=objects.shapes,
            directions=pose_to_cartesian(grid.theta_deg, grid.phi_deg).reshape(-1, 3),
        )


def _project(cameras: PinholeCameras, objects: SceneObjects, lo: int, hi: int) -> FloatArray:
    """Unclipped boxes ``(hi − lo, M, 4)`` of every object at poses ``lo:hi``."""
    cam = PinholeCameras(
        cameras.rotation[lo:hi],
        cameras.position[lo:hi],
        cameras.focal_px,
        cameras.cx,
        cameras.cy,
        cameras.width,
        cameras.height,
    ).to_camera(objects.points)
    depth = cam[..., 2]
    behind = np.logical_or.reduceat(depth <= NEAR_DEPTH, objects.starts, axis=1)
    uv = cam[..., :2] / np.maximum(depth, NEAR_DEPTH)[..., np.newaxis]
    uv = uv * cameras.focal_px + np.array([cameras.cx, cameras.cy])
    boxes = np.concatenate(
        [
            np.minimum.reduceat(uv, objects.starts, axis=1),
            np.maximum.reduceat(uv, objects.starts, axis=1),
        ],
        axis=-1,
    )
    boxes[behind] = np.nan
    return boxes


class GridViewCache(LruFront[GridViews]):
    """:class:`GridViews` per scene (its id and file version), grid and camera, bounded by bytes
    (a 7.5° grid of 20 objects weighs ~300 kB; a 1° grid ~50 MB)."""

    def __init__(self, max_bytes: int = 256 * 1024 * 1024) -> None:
        self._lru = SharedLru[GridViews](max_bytes, weigh=array_nbytes)

    def get(
        self,
        key: Hashable,
        objects: Callable[[], SceneObjects],
        grid: HemisphereGrid,
        camera: CameraSpec,
    ) -> GridViews:
        """The views of ``key``'s scene, projected (:meth:`GridViews.of`) from ``objects()``
        (called on a miss only) when not kept."""
        return self._lru.get(key, lambda: GridViews.of(objects(), grid, camera))


@dataclass(frozen=True)
class StartPrediction:
    """The predicted start: the status (module docstring), the best grid pose (flat index, or
    None without any pair), its score, RMS box-edge difference (pixels) and pairs, the distant
    poses that score alike (flat, score), and why."""

    status: StartStatus
    flat: int | None
    score: float | None
    rms_px: float | None
    pairs: int
    alternatives: tuple[tuple[int, float], ...]
    reason: str


def _pair_costs(views: GridViews, target: Observation, poses: NDArray[np.intp]) -> FloatArray:
    """Pair costs ``(P, D, M)`` at ``poses`` (module docstring); inf where no pair is allowed."""
    predicted = views.boxes[poses]  # (P, M, 4)
    diff = target.boxes[np.newaxis, :, np.newaxis, :] - predicted[:, np.newaxis, :, :]
    cost = np.sum(diff * diff, axis=-1) / (4.0 * SCALE_PX**2)
    labels = np.asarray(target.labels, dtype=object)[:, np.newaxis]
    if target.identity:
        extra = np.where(labels == np.asarray(views.labels, dtype=object), 0.0, np.inf)
    else:
        extra = np.where(labels == np.asarray(views.shapes, dtype=object), 0.0, SHAPE_MISMATCH_COST)
    cost = cost + extra[np.newaxis]
    return np.where(np.isfinite(cost), cost, np.inf)


def _coarse(views: GridViews, target: Observation) -> FloatArray:
    """Every pose's cheap score: each detection's best partner and each expected object's, not
    one-to-one (never above the exact score)."""
    n = len(views.boxes)
    out = np.empty(n)
    per_pose = max(1, len(target) * max(len(views.labels), 1))
    chunk = max(1, _COSTS_PER_CHUNK // per_pose)
    for lo in range(0, n, chunk):
        poses = np.arange(lo, min(n, lo + chunk))
        cost = _pair_costs(views, target, poses)
        targets = cost.min(axis=2, initial=GATE).sum(axis=1)
        lonely = views.expected[poses] & (cost.min(axis=1, initial=GATE) >= GATE)
        out[poses] = targets + MISSING_WEIGHT * GATE * lonely.sum(axis=1)
    return out


def _exact(
    views: GridViews, target: Observation, poses: NDArray[np.intp]
) -> tuple[FloatArray, list[Assignment]]:
    """Exact scores (gated Hungarian, module docstring) and pairs at ``poses``."""
    cost = _pair_costs(views, target, poses)
    scores = np.empty(len(poses))
    pairs = []
    for i, pose in enumerate(poses):
        assignment = assign(cost[i], GATE)
        expected = views.expected[pose]
        unpaired = int(expected.sum()) - int(expected[assignment.cols].sum())
        scores[i] = (
            float(np.minimum(assignment.costs, GATE).sum())
            + GATE * (len(target) - len(assignment))
            + MISSING_WEIGHT * GATE * unpaired
        )
        pairs.append(assignment)
    return scores, pairs


def predict_start(
    views: GridViews,
    grid: HemisphereGrid,
    target: Observation,
    ambiguity_ratio: float = AMBIGUITY_RATIO,
) -> StartPrediction:
    """The grid pose whose predicted view explains ``target`` best, and whether to trust it
    (module docstring). ``target`` is in the scene camera's pixels; in identity mode
    (``target.classes`` given) its labels are the scene's object classes."""
    if len(target) == 0:
        return StartPrediction("failed", None, None, None, 0, (), "no target detection")
    coarse = _coarse(views, target)
    near = np.argsort(coarse, kind="stable")[:NEAR_CANDIDATES].astype(np.intp)
    scores, pairs = _exact(views, target, near)
    order = np.argsort(scores, kind="stable")
    best_i = int(order[0])
    best, best_score, best_pairs = int(near[best_i]), float(scores[best_i]), pairs[best_i]
    threshold = best_score * ambiguity_ratio + AMBIGUITY_MARGIN
    separation = max(1.5 * grid.angle_step_deg, MIN_RIVAL_DEG)
    far = views.directions @ views.directions[best] < math.cos(math.radians(separation))
    rivals_coarse = np.flatnonzero(far & (coarse <= threshold))
    rivals_coarse = rivals_coarse[np.argsort(coarse[rivals_coarse], kind="stable")][:MAX_RIVALS]
    rival_scores, _ = _exact(views, target, rivals_coarse.astype(np.intp))
    alike = rival_scores <= threshold
    alternatives = tuple(
        (int(f), float(s))
        for f, s in sorted(
            zip(rivals_coarse[alike], rival_scores[alike], strict=True), key=lambda fs: fs[1]
        )
    )[:MAX_ALTERNATIVES]
    paired = len(best_pairs)
    rms = _rms(views, target, best, best_pairs)
    where = f"lat {grid.unflat(best).lat} lon {grid.unflat(best).lon}"
    if paired == 0:
        return StartPrediction(
            "failed", None, None, None, 0, (), "no target detection pairs with an object"
        )
    if 2 * paired < len(target):
        return StartPrediction(
            "failed",
            best,
            best_score,
            rms,
            paired,
            alternatives,
            f"the scene's layout does not explain the target: at best ({where}) only {paired} "
            f"of its {len(target)} detections pair with an object",
        )
    if alternatives or paired < 2:
        why = (
            f"{len(alternatives)} distant pose(s) explain the target almost as well"
            if alternatives
            else "a single detection pairs with an object"
        )
        return StartPrediction(
            "ambiguous", best, best_score, rms, paired, alternatives, f"ambiguous: {why}"
        )
    return StartPrediction(
        "found",
        best,
        best_score,
        rms,
        paired,
        (),
        f"predicted {where}: {paired} of {len(target)} detections pair with the scene's "
        f"objects, edge RMS {rms:.2f} px",
    )


def _rms(views: GridViews, target: Observation, pose: int, pairs: Assignment) -> float | None:
    """RMS box-edge difference (pixels) of ``pairs`` at ``pose``; None without pairs."""
    if len(pairs) == 0:
        return None
    diff = target.boxes[pairs.rows] - views.boxes[pose, pairs.cols]
    return float(np.sqrt(np.mean(diff * diff)))
