"""``simple`` — the paper's step-by-step baseline (Fig. 6a).

One N/S/E/W move per iteration: first along the meridian to the ring of the estimated target,
then around that ring the shorter way. The estimate compares the object layout seen *now* with
the target's: the current view's objects are mapped to the ground (exact method) and projected
into every grid pose, and the pose whose projected layout best matches the target's detections is
the estimate (:mod:`services.optimizer.reprojection` with a one-view map). It keeps no memory
beyond that one view — the latest of the visited views that map the most objects reliably,
usually the current one, but not a view with objects hidden or cut off, nor one from the horizon
(θ = 90°), from where nothing can be mapped — so, like the paper's baseline, it can oscillate
where single views mislead; the service then flags the answer ``stuck``. With a correct estimate
it needs exactly the grid distance ``|Δlat| + ring steps``; the worst case is from the pole to
the far side of the equator, 12 + 24 = 36 moves at Δ = 7.5° (π/24).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Final

from services.common.grid import Direction, HemisphereGrid
from services.common.scene import Camera
from services.optimizer.matching import compare_views
from services.optimizer.observations import Observation
from services.optimizer.problem import Plan, SearchProblem, Visit
from services.optimizer.strategies.done import done_plan
from services.optimizer.strategies.map_based import (
    MapEstimate,
    Mapped,
    map_views,
    plan_estimate,
    score_map,
)
from services.optimizer.strategies.moves import explore, neighbour_flat, start_plan
from services.optimizer.view_cache import SHARED_MAPPINGS, ViewMappings

__all__ = ["decision_key", "plan_simple"]

_CACHED_GRID_POSES: Final = 2_000  # larger grids: predictions too heavy to keep many of
_MAPPED_VIEWS: Final = 512
"""Views kept mapped into every pose (keyed by content and pose, so searches of one scene share
them): all of a 341-pose grid's, which the offline simulator revisits for every target (64 made
it 40 % slower). One weighs ~60 kB on 341 poses, in proportion to the grid's size."""
_SCORED_VIEWS: Final = 64
"""Maps kept scored against a target: a simple search reuses one at a time."""


def _mapped_single(
    observation: Observation,
    flat: int,
    theta_deg: float,
    phi_deg: float,
    grid: HemisphereGrid,
    camera: Camera,
    mappings: ViewMappings | None = None,
) -> Mapped:
    """One view alone, mapped and predicted into every grid pose; cached per view by content
    (a search's requests resend its reference view as new objects) unless the grid is so large
    that the cached predictions would weigh too much."""
    if grid.size > _CACHED_GRID_POSES:
        return map_views([Visit(flat, theta_deg, phi_deg, observation)], grid, camera, mappings)
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
    camera: Camera,
    mappings: ViewMappings | None,
) -> Mapped:
    return map_views([Visit(flat, theta_deg, phi_deg, view.observation)], grid, camera, mappings)


@functools.lru_cache(maxsize=_SCORED_VIEWS)
def _scored_cached(
    mapped: Mapped, target: _ByContent, grid: HemisphereGrid, ambiguity_ratio: float
) -> MapEstimate | None:
    """:func:`score_map`, cached per (map, target): the simple search asks it again at every step
    that keeps its reference view (the map is the cached one of that view, so the same object)."""
    return score_map(mapped, target.observation, grid, ambiguity_ratio)


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


def decision_key(problem: SearchProblem) -> tuple[int, int] | None:
    current = problem.current
    if current is None:
        return None
    reference = _reference_view(problem)
    return (current.flat, -1 if reference is None else reference.flat)


def plan_simple(problem: SearchProblem) -> Plan:
    """The paper's step-by-step search (module docstring)."""
    current = problem.current
    if current is None:
        return start_plan(problem)
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    reference = _reference_view(problem)
    if reference is None:
        done = done_plan(problem, current, comparison, None, False)
        return done or explore(problem, current, "no object of any view so far could be mapped")
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
        found = score_map(mapped, problem.target, grid, problem.ambiguity_ratio)
    else:
        found = _scored_cached(mapped, _ByContent(problem.target), grid, problem.ambiguity_ratio)
    if found is None:  # cannot happen: the reference view maps at least one object
        return explore(problem, current, "no object could be mapped")
    est, refined = plan_estimate(problem, current, found)
    here = est.flat == current.flat
    done = done_plan(
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
    nxt = neighbour_flat(grid, current.flat, direction)
    if nxt is None:  # cannot happen for a goal on the grid; kept for safety
        return explore(problem, current, why)
    return Plan(False, nxt, direction, est, found.ambiguous, found.alternatives, why + found.note)
