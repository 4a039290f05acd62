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

from typing import Final

from services.common.caches import SharedLru, array_nbytes
from services.common.geometry.grid import Direction
from services.optimizer.matching import compare_views
from services.optimizer.problem import Plan, SearchProblem, Visit
from services.optimizer.strategies.done import done_plan
from services.optimizer.strategies.map_based import (
    MapEstimate,
    Mapped,
    estimate_or_done,
    map_views,
    score_map,
)
from services.optimizer.strategies.moves import explore, neighbour_flat, start_plan
from services.optimizer.view_cache import SHARED_MAPPINGS

__all__ = ["decision_key", "plan_simple"]

_MAPPED_BYTES: Final = 32 * 2**20
"""Memory for reference views mapped and predicted into every grid pose: ~60 kB each on a
341-pose grid, in proportion to the grid's poses and the view's objects, so 32 MB keep all of a
341-pose grid's views, which the offline simulator revisits for every target (room for 64 made
it 40 % slower)."""
_SCORED_BYTES: Final = 8 * 2**20
"""Memory for those maps scored against a target: ~5 kB each on a 341-pose grid."""

_mapped_views: Final = SharedLru[Mapped](_MAPPED_BYTES, weigh=array_nbytes)
_scored_views: Final = SharedLru[MapEstimate | None](_SCORED_BYTES, weigh=array_nbytes)


def _reference_estimate(problem: SearchProblem, reference: Visit) -> MapEstimate | None:
    """The reference view alone, mapped and predicted into every grid pose, scored against the
    target.

    Both steps are cached by content (:attr:`~services.optimizer.observations.Observation.digest`)
    and pose: a search's requests resend its reference view and target as new objects, and
    searches of one scene share views. The answer is the fresh one's, also where the refinement
    looks for the view's own anchor (:func:`~.map_based.estimate_or_done`)."""
    grid, camera = problem.grid, problem.camera
    view = (
        reference.observation.digest,
        reference.flat,
        reference.theta_deg,
        reference.phi_deg,
        grid,
        camera,
    )

    def mapped() -> Mapped:
        return map_views([reference], grid, camera, problem.mappings)

    def scored() -> MapEstimate | None:
        map_ = _mapped_views.get(view, mapped)
        return score_map(map_, problem.target, grid, problem.ambiguity_ratio)

    return _scored_views.get((view, problem.target.digest, problem.ambiguity_ratio), scored)


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
    found = _reference_estimate(problem, reference)
    if found is None:  # cannot happen: the reference view maps at least one object
        return explore(problem, current, "no object could be mapped")
    est, here, done = estimate_or_done(problem, current, comparison, found)
    if done is not None:
        return done
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
