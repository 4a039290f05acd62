"""Next-best-pose strategies (paper §3.3 and ours): ``simple``, ``paper`` and ``reprojection``.

Every strategy is a pure function of a :class:`~.problem.SearchProblem` — the grid, the camera,
the target's detections and the visited poses with theirs — to a :class:`~.problem.Plan`.

When is the search done?
------------------------
Only the images decide, never the true pose. The current view's detections are matched to the
target's (:func:`~.matching.compare_views`: pairs of alike class and colour, RMS box-edge
difference over the pairs). A match allows unpaired detections in each image up to a summed
*confidence* of ``max_unmatched``: a target detection at confidence 0.3 without a partner (a
doubtful box the search view, rendered at few samples per pixel, does not reproduce) weighs a
third of a sure one. The search is done when

1. the views match *strictly*: RMS within ``tolerance_px``; or
2. the strategy's own estimate puts the target at the current grid pose and the views match
   *loosely*: RMS within the loose tolerance ``T`` below — or, for the map-based strategies,
   the map's prediction at the refined continuous estimate matches the target that closely (a
   target between grid poses).

The strict test alone needs a tolerance below the smallest difference between adjacent grid
views, which can be tiny: near the zenith one 7.5° step in θ moves the demo balls by only
≈ 2 px RMS, less than a real detector's noise. The loose test lets noisy detections and targets
between grid poses finish, but only where the estimate agrees.

The loose tolerance grows with the noise expected of the pairs' box edges. Each edge of pair
``j`` differs between the views by the geometric change ``δ`` plus the two detections' errors,
of standard deviations ``σ_aj``, ``σ_bj`` (:func:`~.observations.edge_sigma`: pixel quantisation
and a fraction of the box size), so the mean squared RMS over the pairs is

.. math:: E[\\mathrm{rms}^2] = δ^2 + N^2, \\qquad
          N^2 = \\frac{1}{P} \\sum_j (σ_{aj}^2 + σ_{bj}^2)

(:attr:`~.matching.ViewComparison.noise_px`), and the test is

.. math:: \\mathrm{rms} \\le T = \\sqrt{(3 \\, t)^2 + (z N)^2}, \\qquad z = 2

(``t`` = ``tolerance_px``, z = :data:`NOISE_SIGMAS`). At the true pose (δ = 0) ``rms²/N²``
is a mean of ``4P`` squared standard normals, whose 99th percentile is below z² = 4 already for
two pairs, so a photo or JPEG target of the true pose passes; a neighbouring pose passes only
with ``δ² < 9 t² + 3 N²`` *and* the estimate at that pose, which the estimate rules out where
neighbouring views differ that little. The strict test is not grown: it has no estimate to rule
out a neighbour.

Strategies
----------
``simple`` — the paper's step-by-step baseline (Fig. 6a). One N/S/E/W move per iteration:
first along the meridian to the ring of the estimated target, then around that ring the shorter
way. The estimate compares the object layout seen *now* with the target's: the current view's
objects are mapped to the ground (exact method) and projected into every grid pose, and the
pose whose projected layout best matches the target's detections is the estimate
(:mod:`.reprojection` with a one-view map). It keeps no memory beyond that one view — the
latest of the visited views that map the most objects reliably, usually the current one, but
not a view with objects hidden or cut off, nor one from the horizon (θ = 90°), from where
nothing can be mapped — so, like the paper's baseline, it can oscillate where single views
mislead; the service then flags the answer ``stuck``. With a correct estimate it needs
exactly the grid distance ``|Δlat| + ring steps``; the worst case is from the pole to the far
side of the equator, 12 + 24 = 36 moves at Δ = 7.5° (π/24).

``paper`` — the optimised search of §3.3: the current view mapped by the paper's eq. 2–7,
latitude from the distance-to-centre profile over every candidate camera height, longitude from
the rotation solve (:mod:`.layout`), then a jump to the grid pose nearest the estimate. If the
estimate points at the current pose but the views differ, it steps to the neighbour nearest the
continuous estimate.

``reprojection`` (ours, the default) — a world map fused from every visited view
(:mod:`.world_map`, exact mapping); every grid pose is scored by projecting the map into it and
matching the target's detections (:mod:`.reprojection`); the camera jumps to the best pose not
yet visited. At the best pose the continuous (θ, φ) is refined by least-squares reprojection —
also when the best pose is another visited one than the current: a target between grid poses may
look more like a farther grid pose's view than its nearest one's (near the zenith a change of φ
turns the whole image), and the refined pose then says the current pose is the nearest; the
map's prediction there must then pair the target's detections (unpaired confidence within
``max_unmatched``), as the current view must otherwise.

Ambiguity
---------
Map-based answers list poses more than 1.5 grid steps from the best whose scores come within
``ambiguity_ratio`` of it (plus a margin of one object off by 4 px) as alternatives and flag the
answer ambiguous — a symmetric layout, or too few objects to pin the pose down (fewer than two
target detections matched). The layout estimate is ambiguous when fewer than two objects match
or they disagree on the rotation.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, replace
from typing import Final, Literal

import numpy as np
from numpy.typing import NDArray

from services.common.geometry.grid import (
    Direction,
    HemisphereGrid,
    angular_distance_deg,
    pose_to_cartesian,
)
from services.common.geometry.pose import GridIndex
from services.common.geometry.scene import CameraSpec
from services.optimizer.geometry import PinholeCameras
from services.optimizer.layout import LayoutEstimate, estimate_layout
from services.optimizer.matching import Assignment, ViewComparison, compare_views
from services.optimizer.observations import Observation
from services.optimizer.problem import Estimate, Move, Plan, SearchProblem, Visit
from services.optimizer.reprojection import (
    SCALE_PX,
    Anchor,
    Anchoring,
    PoseScores,
    Prediction,
    predict,
    refine_pose,
    score_poses,
)
from services.optimizer.view_cache import SHARED_MAPPINGS, ViewMappings
from services.optimizer.world_map import MappedView, WorldMap, build_map

__all__ = [
    "DEFAULT_STRATEGY",
    "LOOSE_FACTOR",
    "NOISE_SIGMAS",
    "STRATEGIES",
    "CalibrationMissingError",
    "StrategyName",
    "StrategySpec",
    "default_start",
    "grid_cameras",
    "move_between",
    "plan_next",
]

StrategyName = Literal["simple", "paper", "reprojection"]
DEFAULT_STRATEGY: Final[StrategyName] = "reprojection"

LOOSE_FACTOR: Final = 3.0
"""The loose done test's tolerance before noise, in strict tolerances (module docstring)."""
NOISE_SIGMAS: Final = 2.0
"""z: standard deviations of edge noise the loose done test allows (module docstring)."""
_AMBIGUITY_MARGIN: Final = 1.0  # score units: one object off by SCALE_PX pixels
_MAX_ALTERNATIVES: Final = 5
_CACHED_GRID_POSES: Final = 2_000  # larger grids: predictions too heavy to keep many of
_MAPPED_VIEWS: Final = 512
"""Views kept mapped into every pose (keyed by content and pose, so searches of one scene share
them): all of a 341-pose grid's, which the offline simulator revisits for every target (64 made
it 40 % slower). One weighs ~60 kB on 341 poses, in proportion to the grid's size."""
_SCORED_VIEWS: Final = 64
"""Maps kept scored against a target: a simple search reuses one at a time."""


class CalibrationMissingError(ValueError):
    """The strategy needs the paper mapping's coefficients and none are stored for the camera."""


@dataclass(frozen=True)
class StrategySpec:
    """A registered strategy.

    ``decision_key``, when given, names everything besides the target a decision depends on
    (e.g. the current pose), so a simulator may cache decisions by it; None means the whole
    history matters.
    """

    name: StrategyName
    description: str
    plan: Callable[[SearchProblem], Plan]
    needs_calibration: bool
    decision_key: Callable[[SearchProblem], Hashable] | None


# -- helpers -----------------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def grid_cameras(grid: HemisphereGrid, camera: CameraSpec) -> PinholeCameras:
    """PinholeCameras at every grid pose (flat order), built once per grid and camera."""
    return PinholeCameras.at(grid.theta_deg, grid.phi_deg, camera)


@functools.lru_cache(maxsize=16)
def _grid_units(grid: HemisphereGrid) -> NDArray[np.float64]:
    """Unit view directions of every grid pose (flat order)."""
    return pose_to_cartesian(grid.theta_deg, grid.phi_deg)


def default_start(grid: HemisphereGrid) -> int:
    """A start pose that sees the scene well: lon 0 of the ring nearest θ = 45°."""
    return grid.flat(GridIndex(lat=_ring_of(grid, 45.0), lon=0))


def move_between(grid: HemisphereGrid, a: int, b: int) -> Move:
    """The move from flat pose ``a`` to ``b``: a direction when they are neighbours."""
    if a == b:
        return "stay"
    for direction, neighbour in grid.neighbours(grid.unflat(a)).items():
        if grid.flat(neighbour) == b:
            return direction
    return "jump"


def _step(grid: HemisphereGrid, flat: int, direction: Direction) -> int | None:
    neighbour = grid.neighbour(grid.unflat(flat), direction)
    return None if neighbour is None else grid.flat(neighbour)


def _ring_of(grid: HemisphereGrid, theta_deg: float) -> int:
    rings = np.array([ring.theta_deg for ring in grid.rings])
    return int(np.argmin(np.abs(rings - theta_deg)))


def _wrap180(angle: float) -> float:
    return (angle + 180.0) % 360.0 - 180.0


def _explore(problem: SearchProblem, current: Visit, why: str) -> Plan:
    """A fallback move when nothing can be estimated: towards the zenith (views there map best),
    else around the ring, else away from the zenith."""
    directions: tuple[Direction, ...] = ("N", "E", "S")
    for direction in directions:
        nxt = _step(problem.grid, current.flat, direction)
        if nxt is not None:
            return Plan(False, nxt, direction, None, True, (), why)
    return Plan(False, current.flat, "stay", None, True, (), why)


def _start(problem: SearchProblem) -> Plan:
    return Plan(
        done=False,
        next_flat=default_start(problem.grid),
        move="start",
        estimate=None,
        ambiguous=False,
        alternatives=(),
        reason="no view yet: render this start pose and send its detections in the history",
    )


def _matched_text(comparison: ViewComparison) -> str:
    if math.isinf(comparison.rms_px):
        return "no detection pairs with the target"
    text = (
        f"RMS {comparison.rms_px:.2f} px over {len(comparison.pairs)} pairs "
        f"(edge noise {comparison.noise_px:.2f} px), "
        f"{comparison.unmatched_a} current / {comparison.unmatched_b} target unpaired"
    )
    if comparison.unmatched_a or comparison.unmatched_b:
        text += f" (confidence {comparison.unpaired_a:.2f} / {comparison.unpaired_b:.2f})"
    return text


def _done(
    problem: SearchProblem,
    current: Visit,
    comparison: ViewComparison,
    est: Estimate | None,
    here: bool,
    refined: _Refined | None = None,
    ambiguous: bool = False,
    alternatives: tuple[tuple[int, float], ...] = (),
) -> Plan | None:
    """The done test shared by every strategy (module docstring), or None to keep searching.

    ``refined`` is a map-based strategy's refined continuous estimate nearest the current
    pose: its residual compares the target with the map's prediction at the off-grid pose."""
    tol = problem.tolerance_px
    if comparison.within(tol, problem.max_unmatched):
        if est is None or est.flat != current.flat:
            # The views match: the target is here, whatever a coarser estimate said.
            coverage = len(comparison.pairs) / max(len(problem.target), 1)
            est = Estimate(
                current.flat,
                current.theta_deg,
                current.phi_deg,
                comparison.rms_px,
                coverage * math.exp(-0.5 * (comparison.rms_px / max(tol, 2.0)) ** 2),
            )
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the current view matches the target within {tol:g} px ({_matched_text(comparison)})",
        )  # fmt: skip
    if not here:
        return None
    loose = comparison.tolerance(LOOSE_FACTOR * tol, NOISE_SIGMAS)
    if comparison.within(loose, problem.max_unmatched):
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the estimate puts the target at this grid pose and the views agree within "
            f"{loose:.2f} px ({_matched_text(comparison)})",
        )  # fmt: skip
    if refined is None or refined.residual_px > loose:
        return None
    # Refined at another view, the prediction pairs the target, not this view (which may look
    # less like the target than that one does).
    if refined.elsewhere:
        paired = refined.unpaired_target <= problem.max_unmatched
    else:
        paired = comparison.paired(problem.max_unmatched)
    refined_px = refined.residual_px
    if paired:
        assert est is not None  # a refined residual comes with its estimate
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the target lies between grid poses, nearest this one: at the refined pose "
            f"θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° the predicted view matches it "
            f"within {refined_px:.2f} px (the grid view differs by {comparison.rms_px:.2f} px)",
        )  # fmt: skip
    return None


# -- the map-based estimate, shared by simple and reprojection ---------------------------------


@dataclass(frozen=True)
class _MapEstimate:
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
    def note(self) -> str:
        return ("; ambiguous: " + "; ".join(self.reasons)) if self.reasons else ""


_Mapped = tuple[WorldMap, tuple[Anchor, ...], Anchoring, Prediction]


def _mapped(
    visits: Sequence[Visit],
    grid: HemisphereGrid,
    camera: CameraSpec,
    mappings: ViewMappings | None = None,
) -> _Mapped:
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


def _mapped_single(
    observation: Observation,
    flat: int,
    theta_deg: float,
    phi_deg: float,
    grid: HemisphereGrid,
    camera: CameraSpec,
    mappings: ViewMappings | None = None,
) -> _Mapped:
    """One view alone, mapped and predicted into every grid pose; cached per view by content
    (a search's requests resend its reference view as new objects) unless the grid is so large
    that the cached predictions would weigh too much."""
    if grid.size > _CACHED_GRID_POSES:
        return _mapped([Visit(flat, theta_deg, phi_deg, observation)], grid, camera, mappings)
    return _mapped_single_cached(
        _ByContent(observation), flat, theta_deg, phi_deg, grid, camera, mappings
    )


@dataclass(frozen=True, eq=False)
class _ByContent:
    """An observation as a cache key: equal when the contents are (:attr:`Observation.digest`)."""

    observation: Observation

    def __hash__(self) -> int:
        return hash(self.observation.digest)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _ByContent) and other.observation.digest == self.observation.digest


@functools.lru_cache(maxsize=_MAPPED_VIEWS)
def _mapped_single_cached(
    view: _ByContent,
    flat: int,
    theta_deg: float,
    phi_deg: float,
    grid: HemisphereGrid,
    camera: CameraSpec,
    mappings: ViewMappings | None,
) -> _Mapped:
    return _mapped([Visit(flat, theta_deg, phi_deg, view.observation)], grid, camera, mappings)


def _map_estimate(problem: SearchProblem, mapped: _Mapped) -> _MapEstimate | None:
    """The map's best poses for the target, alternatives and ambiguity."""
    return _scored(mapped, problem.target, problem.grid, problem.ambiguity_ratio)


@functools.lru_cache(maxsize=_SCORED_VIEWS)
def _scored_cached(
    mapped: _Mapped, target: _ByContent, grid: HemisphereGrid, ambiguity_ratio: float
) -> _MapEstimate | None:
    """:func:`_scored`, cached per (map, target): the simple search asks it again at every step
    that keeps its reference view (the map is the cached one of that view, so the same object)."""
    return _scored(mapped, target.observation, grid, ambiguity_ratio)


def _scored(
    mapped: _Mapped, target: Observation, grid: HemisphereGrid, ambiguity_ratio: float
) -> _MapEstimate | None:
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
    return _MapEstimate(world, anchors, anchoring, scores, tuple(alternatives), tuple(reasons))


def _theta_bounds(grid: HemisphereGrid) -> tuple[float, float]:
    step = grid.angle_step_deg
    return (
        max(0.0, float(grid.theta_deg[0]) - step),
        min(90.0, float(grid.theta_deg[-1]) + step),
    )


@dataclass(frozen=True)
class _Refined:
    """A refined continuous estimate that puts the target nearest the current grid pose.

    ``residual_px`` is its reprojection residual; ``elsewhere`` is set when it was refined at
    another visited pose (the best-scoring one, anchored to its own view), and then
    ``unpaired_target`` is the summed confidence of target detections the map left unpaired
    there."""

    residual_px: float
    elsewhere: bool = False
    unpaired_target: float = 0.0


def _anchored_visit(problem: SearchProblem, found: _MapEstimate, flat: int) -> Visit | None:
    """The latest visit of grid pose ``flat`` whose own view anchors the map's prediction
    there (at least two of its detections joined the map, or all of one), else None."""
    for visit in reversed(problem.history):
        if visit.flat != flat:
            continue
        for a in found.anchors:
            if a.observation is visit.observation:
                if int(np.sum(a.link >= 0)) >= min(2, len(a.link)):
                    return visit
        return None
    return None


def _map_plan_estimate(
    problem: SearchProblem, current: Visit, found: _MapEstimate
) -> tuple[Estimate, _Refined | None]:
    """The estimate of a map-based strategy and, when its refined continuous pose lies nearest
    the current grid pose, that refinement (else None).

    The pose is refined at the best grid pose when a view of it anchors the map's prediction
    there: the current pose, or another visited pose. The latter is a target between grid
    poses whose nearest grid pose looks less like it than a farther one does (near the zenith
    a change of φ turns the whole image), which would otherwise send the search back and forth
    between the two. The estimate's ``flat`` is the grid pose nearest the refined pose."""
    grid = problem.grid
    coverage = len(found.pairs) / max(len(problem.target), 1)

    def estimate(theta: float, phi: float, residual: float) -> Estimate:
        tol = max(problem.tolerance_px, 2.0)
        confidence = coverage * math.exp(-0.5 * (residual / tol) ** 2)
        confidence /= 1 + len(found.alternatives)
        flat = int(grid.nearest_flat(theta, phi))
        return Estimate(flat, theta, phi, residual, float(np.clip(confidence, 0.0, 1.0)))

    # The refined pose speaks for a grid pose only where the prediction there is anchored to
    # that pose's own view; a map seen from elsewhere is not accurate enough to say that the
    # target lies between grid poses, nor worth refining.
    start = _anchored_visit(problem, found, found.best)
    if start is None or (found.best == current.flat and start is not current):
        residual = SCALE_PX * math.sqrt(float(found.scores.exact[0]) / max(len(found.pairs), 1))
        best = found.best
        return estimate(float(grid.theta_deg[best]), float(grid.phi_deg[best]), residual), None
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
    est = estimate(refined.theta_deg, refined.phi_deg, refined.residual_px)
    if est.flat != current.flat or not math.isfinite(refined.residual_px):
        return est, None
    if start is current:
        return est, _Refined(refined.residual_px)
    target = problem.target.confidence
    unpaired = float(target.sum() - target[found.pairs.rows].sum())
    return est, _Refined(refined.residual_px, elsewhere=True, unpaired_target=unpaired)


# -- simple ------------------------------------------------------------------------------------


def _reliable_count(problem: SearchProblem, visit: Visit) -> int:
    """How many of the view's objects the exact mapping places reliably."""
    if len(visit.observation) == 0:
        return 0
    mappings = SHARED_MAPPINGS if problem.mappings is None else problem.mappings
    mapped = mappings.get(visit.observation, visit.theta_deg, visit.phi_deg, problem.camera)
    return int(mapped.reliable.sum())


def _reference_view(problem: SearchProblem) -> Visit | None:
    """The view the simple search maps: the latest of those placing the most objects reliably.

    Usually the current view; an earlier one when the current view maps fewer objects (some
    hidden, or cut by the border) or none (on the horizon, where an object twice as large and
    twice as far looks the same), so that one poor view does not turn the search around."""
    counts = [_reliable_count(problem, v) for v in problem.history]
    if not counts or max(counts) == 0:
        return None
    best = max(counts)
    last = max(i for i, n in enumerate(counts) if n == best)
    return problem.history[last]


def _simple_key(problem: SearchProblem) -> tuple[int, int] | None:
    current = problem.current
    if current is None:
        return None
    reference = _reference_view(problem)
    return (current.flat, -1 if reference is None else reference.flat)


def plan_simple(problem: SearchProblem) -> Plan:
    """The paper's step-by-step search (module docstring)."""
    current = problem.current
    if current is None:
        return _start(problem)
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    reference = _reference_view(problem)
    if reference is None:
        done = _done(problem, current, comparison, None, False)
        return done or _explore(problem, current, "no object of any view so far could be mapped")
    mapped = _mapped_single(
        reference.observation,
        reference.flat,
        reference.theta_deg,
        reference.phi_deg,
        grid,
        problem.camera,
        problem.mappings,
    )
    if grid.size > _CACHED_GRID_POSES:
        found = _scored(mapped, problem.target, grid, problem.ambiguity_ratio)
    else:
        found = _scored_cached(mapped, _ByContent(problem.target), grid, problem.ambiguity_ratio)
    if found is None:  # cannot happen: the reference view maps at least one object
        return _explore(problem, current, "no object could be mapped")
    est, refined = _map_plan_estimate(problem, current, found)
    here = est.flat == current.flat
    done = _done(
        problem, current, comparison, est, here, refined, found.ambiguous, found.alternatives
    )
    if done is not None:
        return replace(done, reason=done.reason + found.note)
    goal = est.flat
    if here:  # the estimate says "here" but the views differ: head for the runner-up
        goal = next((int(f) for f in found.scores.candidates if int(f) != current.flat), goal)
    index, target_index = grid.unflat(current.flat), grid.unflat(goal)
    if target_index.lat != index.lat:
        direction: Direction = "N" if target_index.lat < index.lat else "S"
        why = (
            f"latitude first: the estimated target ring is θ = "
            f"{grid.rings[target_index.lat].theta_deg:g}°, "
            f"{abs(target_index.lat - index.lat)} ring(s) {'up' if direction == 'N' else 'down'}"
        )
    else:
        n = grid.ring_size(index.lat)
        ahead = (target_index.lon - index.lon) % n
        direction = "E" if ahead <= n / 2 else "W"
        why = (
            f"on the estimated target ring; longitude {min(ahead, n - ahead)} step(s) "
            f"{'east' if direction == 'E' else 'west'}, the shorter way"
        )
    nxt = _step(grid, current.flat, direction)
    if nxt is None:  # cannot happen for a goal on the grid; kept for safety
        return _explore(problem, current, why)
    return Plan(False, nxt, direction, est, found.ambiguous, found.alternatives, why + found.note)


# -- paper -------------------------------------------------------------------------------------


def _current_key(problem: SearchProblem) -> int | None:
    return None if problem.current is None else problem.current.flat


def _layout(problem: SearchProblem, current: Visit) -> LayoutEstimate:
    if problem.calibration is None:
        raise CalibrationMissingError(
            "no paper-mapping coefficients are stored for this camera configuration; "
            "run tools/fit_paper_mapping.py or use another strategy"
        )
    return estimate_layout(
        problem.target,
        current.observation,
        current.theta_deg,
        current.phi_deg,
        problem.camera,
        problem.grid,
        problem.calibration,
    )


def _layout_estimate(problem: SearchProblem, est: LayoutEstimate) -> Estimate:
    flat = int(problem.grid.nearest_flat(est.theta_deg, est.phi_deg))
    # The rotation fit's ground residual in pixels at the scene centre's scale f / r.
    scale = PinholeCameras.at(0.0, 0.0, problem.camera).focal_px / problem.camera.radius
    residual_px = est.residual * scale
    coverage = est.matched / max(len(problem.target), 1)
    tol = max(problem.tolerance_px, 2.0)
    confidence = coverage * est.coherence * math.exp(-0.5 * (residual_px / tol) ** 2)
    if est.ambiguous:
        confidence *= 0.5
    return Estimate(flat, est.theta_deg, est.phi_deg, residual_px, float(np.clip(confidence, 0, 1)))


def plan_paper(problem: SearchProblem) -> Plan:
    """The paper's optimised search (module docstring)."""
    current = problem.current
    if current is None:
        return _start(problem)
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    layout = _layout(problem, current)
    est = _layout_estimate(problem, layout) if layout.ok else None
    here = est is not None and est.flat == current.flat
    done = _done(problem, current, comparison, est, here, ambiguous=layout.ambiguous)
    if done is not None:
        return done
    if est is None:
        return _explore(problem, current, f"cannot estimate the target: {layout.reason}")
    note = f" ({layout.reason})" if layout.reason else ""
    if not here:
        return Plan(
            False, est.flat, move_between(grid, current.flat, est.flat), est, layout.ambiguous,
            (),
            f"jump to the grid pose nearest the estimate θ = {layout.theta_deg:.1f}°, "
            f"φ = {layout.phi_deg:.1f}°" + note,
        )  # fmt: skip
    neighbours = [grid.flat(nb) for nb in grid.neighbours(grid.unflat(current.flat)).values()]
    if not neighbours:
        return Plan(False, current.flat, "stay", est, True, (), "no neighbour to try")
    angles = angular_distance_deg(
        (grid.theta_deg[neighbours], grid.phi_deg[neighbours]), (layout.theta_deg, layout.phi_deg)
    )
    nxt = neighbours[int(np.argmin(angles))]
    return Plan(
        False, nxt, move_between(grid, current.flat, nxt), est, True, (),
        f"the estimate points here but the views differ ({_matched_text(comparison)}); "
        "trying the neighbour nearest the continuous estimate" + note,
    )  # fmt: skip


# -- reprojection ------------------------------------------------------------------------------


def plan_reprojection(problem: SearchProblem) -> Plan:
    """Our map-based search (module docstring)."""
    current = problem.current
    if current is None:
        return _start(problem)
    grid = problem.grid
    found = _map_estimate(problem, _mapped(problem.history, grid, problem.camera, problem.mappings))
    comparison = compare_views(current.observation, problem.target)
    if found is None:
        done = _done(problem, current, comparison, None, False)
        return done or _explore(problem, current, "no object could be mapped from the views")
    est, refined = _map_plan_estimate(problem, current, found)
    here = est.flat == current.flat
    done = _done(
        problem, current, comparison, est, here, refined, found.ambiguous, found.alternatives
    )
    if done is not None:
        return replace(done, reason=done.reason + found.note)
    visited = {v.flat for v in problem.history}
    if found.best == current.flat and not here:
        nxt = est.flat
        why = (
            f"the refined estimate θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° lies "
            "nearer this grid pose"
        )
    else:
        unvisited = [int(f) for f in found.scores.candidates if int(f) not in visited]
        nxt = unvisited[0] if unvisited else found.best
        why = "jump to the best-scoring grid pose"
    if nxt != found.best and nxt != est.flat:
        why = (
            "the best-scoring pose was visited and its view does not match the target "
            f"({_matched_text(comparison)}); trying the best unvisited pose"
        )
    return Plan(
        False, nxt, move_between(grid, current.flat, nxt), est, found.ambiguous,
        found.alternatives, why + found.note,
    )  # fmt: skip


STRATEGIES: Final[dict[str, StrategySpec]] = {
    "simple": StrategySpec(
        "simple",
        "The paper's step-by-step baseline (Fig. 6a): one N/S/E/W move per iteration, "
        "latitude first, then longitude the shorter way, towards the pose whose projected "
        "layout of the current view best matches the target.",
        plan_simple,
        needs_calibration=False,
        decision_key=_simple_key,
    ),
    "paper": StrategySpec(
        "paper",
        "The paper's optimised search (§3.3): latitude from the distance-to-centre profile, "
        "longitude from the rotation solve (paper mapping, eq. 2-8), jump to the nearest grid "
        "pose.",
        plan_paper,
        needs_calibration=True,
        decision_key=_current_key,
    ),
    "reprojection": StrategySpec(
        "reprojection",
        "Ours: fuse a world map from every view, score every grid pose by reprojecting it and "
        "matching the target (Hungarian on class, colour, position), jump to the best, refine "
        "θ/φ continuously when converged.",
        plan_reprojection,
        needs_calibration=False,
        decision_key=None,
    ),
}


def plan_next(problem: SearchProblem, strategy: str = DEFAULT_STRATEGY) -> Plan:
    """Plan the next step with the named strategy.

    Raises
    ------
    KeyError
        Unknown strategy.
    CalibrationMissingError
        The strategy needs paper coefficients that are not stored for the camera.
    """
    return STRATEGIES[strategy].plan(problem)
