"""The map-based estimate shared by ``simple`` and ``reprojection``: map views, score every grid
pose against the target, flag ambiguity, and refine the continuous pose.

Ambiguity
---------
Map-based answers list poses more than 1.5 grid steps from the best whose scores come within
``ambiguity_ratio`` of it (plus a margin of one object off by 4 px) as alternatives and flag the
answer ambiguous — a symmetric layout, or too few objects to pin the pose down (fewer than two
target detections matched).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer.geometry import PinholeCameras
from services.optimizer.matching import Assignment, ViewComparison
from services.optimizer.observations import Observation
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit
from services.optimizer.reprojection import (
    SCALE_PX,
    Anchor,
    Anchoring,
    PoseScores,
    Prediction,
    Refinement,
    predict,
    refine_pose,
    score_poses,
)
from services.optimizer.strategies.done import Refined, Rival, done_plan
from services.optimizer.view_cache import ViewMappings
from services.optimizer.world_map import MappedView, WorldMap, build_map

__all__ = [
    "MapEstimate",
    "Mapped",
    "estimate_or_done",
    "grid_cameras",
    "map_estimate",
    "map_views",
    "plan_estimate",
    "score_map",
]

_AMBIGUITY_MARGIN: Final = 1.0  # score units: one object off by SCALE_PX pixels
_MAX_ALTERNATIVES: Final = 5


@functools.lru_cache(maxsize=16)
def grid_cameras(grid: HemisphereGrid, camera: CameraSpec) -> PinholeCameras:
    """PinholeCameras at every grid pose (flat order), built once per grid and camera."""
    return PinholeCameras.at(grid.theta_deg, grid.phi_deg, camera)


@functools.lru_cache(maxsize=16)
def _grid_units(grid: HemisphereGrid) -> NDArray[np.float64]:
    """Unit view directions of every grid pose (flat order)."""
    return pose_to_cartesian(grid.theta_deg, grid.phi_deg)


@dataclass(frozen=True)
class MapEstimate:
    """A map's scores of every grid pose for the target, best first, and its ambiguity."""

    world: WorldMap
    anchors: tuple[Anchor, ...]
    anchoring: Anchoring
    scores: PoseScores
    alternatives: tuple[tuple[int, float], ...]
    reasons: tuple[str, ...]

    @property
    def best(self) -> int:
        return int(self.scores.candidates[0])

    @property
    def pairs(self) -> Assignment:
        return self.scores.pairs[0]

    @property
    def ambiguous(self) -> bool:
        return bool(self.reasons)

    @property
    def checks(self) -> tuple[int, ...] | None:
        """The grid poses whose views settle the map's ambiguity: its alternatives; None when
        too few target detections match the map, which no view settles."""
        if len(self.pairs) < 2:
            return None
        return tuple(flat for flat, _ in self.alternatives)

    @property
    def note(self) -> str:
        return ("; ambiguous: " + "; ".join(self.reasons)) if self.reasons else ""


Mapped = tuple[WorldMap, tuple[Anchor, ...], Anchoring, Prediction]
"""A map, its anchors (the views it was fused from), their anchoring and its prediction into
every grid pose."""


def map_views(
    visits: Sequence[Visit],
    grid: HemisphereGrid,
    camera: CameraSpec,
    mappings: ViewMappings | None = None,
) -> Mapped:
    """The visited views fused into one map, anchored to them and predicted into every grid
    pose."""
    views = [MappedView(v.theta_deg, v.phi_deg, v.observation) for v in visits]
    world, links = build_map(views, camera, mappings)
    anchors = tuple(
        Anchor(v.theta_deg, v.phi_deg, v.observation, link)
        for v, link in zip(visits, links, strict=True)
    )
    cameras = grid_cameras(grid, camera)
    boxes, inside = world.boxes(cameras)
    anchoring = Anchoring.of(anchors, boxes[np.array([v.flat for v in visits], dtype=np.intp)])
    prediction = predict(boxes, inside, cameras, anchoring, grid.angle_step_deg)
    return world, anchors, anchoring, prediction


def map_estimate(problem: SearchProblem, mapped: Mapped) -> MapEstimate | None:
    """The map's best poses for the target, alternatives and ambiguity."""
    return score_map(mapped, problem.target, problem.grid, problem.ambiguity_ratio)


def score_map(
    mapped: Mapped, target: Observation, grid: HemisphereGrid, ambiguity_ratio: float
) -> MapEstimate | None:
    """Every grid pose scored by the map's prediction against ``target``, with the distant
    poses that score alike (module docstring); None for an empty map."""
    world, anchors, anchoring, prediction = mapped
    if len(world) == 0:
        return None
    scores = score_poses(
        world,
        target,
        prediction,
        directions=_grid_units(grid),
        separation_deg=1.5 * grid.angle_step_deg,
    )
    best = int(scores.candidates[0])
    threshold = float(scores.exact[0]) * ambiguity_ratio + _AMBIGUITY_MARGIN
    units = _grid_units(grid)
    cosine = units[scores.candidates[1:]] @ units[best]
    far = cosine < math.cos(math.radians(1.5 * grid.angle_step_deg))
    alike = far & (scores.exact[1:] <= threshold)
    alternatives = [
        (int(flat), float(score))
        for flat, score in zip(scores.candidates[1:][alike], scores.exact[1:][alike], strict=True)
    ][:_MAX_ALTERNATIVES]
    reasons = []
    if alternatives:
        reasons.append(f"{len(alternatives)} distant pose(s) explain the target almost as well")
    if len(scores.pairs[0]) < 2:
        reasons.append(f"only {len(scores.pairs[0])} target detection(s) match the mapped objects")
    return MapEstimate(world, anchors, anchoring, scores, tuple(alternatives), tuple(reasons))


def _theta_bounds(grid: HemisphereGrid) -> tuple[float, float]:
    step = grid.angle_step_deg
    return (
        max(0.0, float(grid.theta_deg[0]) - step),
        min(90.0, float(grid.theta_deg[-1]) + step),
    )


def _own_anchors(anchors: Sequence[Anchor], visit: Visit) -> list[Anchor]:
    """The anchors of ``visit``'s own view: those holding its observation, else (a map cached
    from an earlier request, which holds that request's objects) those with equal detections
    at its pose."""
    own = [a for a in anchors if a.observation is visit.observation]
    if own:
        return own
    digest = visit.observation.digest
    return [
        a
        for a in anchors
        if (a.theta_deg, a.phi_deg) == (visit.theta_deg, visit.phi_deg)
        and a.observation.digest == digest
    ]


def _anchored_visit(problem: SearchProblem, found: MapEstimate, flat: int) -> Visit | None:
    """The latest visit of grid pose ``flat`` whose own view anchors the map's prediction
    there (at least two of its detections joined the map, or all of one), else None."""
    for visit in reversed(problem.history):
        if visit.flat != flat:
            continue
        for a in _own_anchors(found.anchors, visit):
            if int(np.sum(a.link >= 0)) >= min(2, len(a.link)):
                return visit
        return None
    return None


def plan_estimate(
    problem: SearchProblem, current: Visit, found: MapEstimate
) -> tuple[Estimate, Refined | None, Rival | None]:
    """The estimate of a map-based strategy; when its refined continuous pose lies nearest the
    current grid pose, that refinement (else None); and the grid pose the estimate cannot rule
    out (:class:`~.done.Rival`), if any: the best-scoring neighbour of an estimate that was not
    refined, or the grid pose nearest a robust fit that lost to its start by RMS.

    The pose is refined at the best grid pose when a view of it anchors the map's prediction
    there: the current pose, or another visited pose. The latter is a target between grid
    poses whose nearest grid pose looks less like it than a farther one does (near the zenith
    a change of φ turns the whole image), which would otherwise send the search back and forth
    between the two. The estimate's ``flat`` is the grid pose nearest the refined pose."""
    grid = problem.grid
    coverage = len(found.pairs) / max(len(problem.target), 1)

    def estimate(theta: float, phi: float, residual: float, sigma: float | None = None) -> Estimate:
        tol = max(problem.tolerance_px, 2.0)
        confidence = coverage * math.exp(-0.5 * (residual / tol) ** 2)
        confidence /= 1 + len(found.alternatives)
        flat = int(grid.nearest_flat(theta, phi))
        return Estimate(flat, theta, phi, residual, float(np.clip(confidence, 0.0, 1.0)), sigma)

    # The refined pose speaks for a grid pose only where the prediction there is anchored to
    # that pose's own view; a map seen from elsewhere is not accurate enough to say that the
    # target lies between grid poses, nor worth refining.
    start = _anchored_visit(problem, found, found.best)
    if start is None or (found.best == current.flat and start is not current):
        residual = SCALE_PX * math.sqrt(float(found.scores.exact[0]) / max(len(found.pairs), 1))
        best = found.best
        est = estimate(float(grid.theta_deg[best]), float(grid.phi_deg[best]), residual)
        return est, None, _best_neighbour(grid, best, found.scores.coarse)
    refined = refine_pose(
        found.world,
        problem.target,
        found.pairs,
        start.theta_deg,
        start.phi_deg,
        problem.camera,
        found.anchoring,
        grid,
        _theta_bounds(grid),
    )
    est = estimate(refined.theta_deg, refined.phi_deg, refined.residual_px, refined.sigma_deg)
    if est.flat != current.flat or not math.isfinite(refined.residual_px):
        return est, None, None
    rival = _fit_elsewhere(grid, est.flat, refined, found.scores.coarse)
    if start is current:
        return est, Refined(refined.residual_px), rival
    target = problem.target.confidence
    unpaired = float(target.sum() - target[found.pairs.rows].sum())
    return est, Refined(refined.residual_px, elsewhere=True, unpaired_target=unpaired), rival


def _best_neighbour(grid: HemisphereGrid, flat: int, scores: NDArray[np.float64]) -> Rival | None:
    """The grid neighbour of ``flat`` with the least map ``scores`` (every pose's cheap score,
    never above its exact one), or None on a grid of one pose."""
    neighbours = [grid.flat(n) for n in grid.neighbours(grid.unflat(flat)).values()]
    if not neighbours:
        return None
    best = min(neighbours, key=lambda f: float(scores[f]))
    why = (
        "the estimate is this grid pose's score, not refined between grid poses (no view "
        "anchors the map's prediction here)"
    )
    return Rival(int(best), float(scores[best]), why)


def _fit_elsewhere(
    grid: HemisphereGrid, flat: int, refined: Refinement, scores: NDArray[np.float64]
) -> Rival | None:
    """The grid pose nearest ``refined``'s robust fit when the start (grid pose ``flat``) was
    kept over it by RMS and the fit lies nearer another grid pose, else None."""
    if not refined.kept_start or refined.fit_deg is None:
        return None
    theta, phi = refined.fit_deg
    other = int(grid.nearest_flat(theta, phi))
    if other == flat:
        return None
    why = (
        f"the robust refinement puts the target at θ = {theta:.2f}°, φ = {phi:.2f}°, nearer "
        f"another grid pose; this one is kept only for its smaller RMS"
    )
    return Rival(other, float(scores[other]), why, settled_by_views=False)


def estimate_or_done(
    problem: SearchProblem, current: Visit, comparison: ViewComparison, found: MapEstimate
) -> tuple[Estimate, bool, Plan | None]:
    """A map-based strategy's estimate, whether it names the current grid pose, and the done
    plan when the done test passes (else None)."""
    est, refined, rival = plan_estimate(problem, current, found)
    here = est.flat == current.flat
    done = done_plan(
        problem,
        current,
        comparison,
        est,
        here,
        refined,
        found.ambiguous,
        found.alternatives,
        rival,
        found.checks,
    )
    return est, here, None if done is None else replace(done, reason=done.reason + found.note)
