"""``reprojection`` (ours, the default) — a search on a world map fused from every view.

A world map fused from every visited view (:mod:`services.optimizer.world_map`, exact mapping);
every grid pose is scored by projecting the map into it and matching the target's detections
(:mod:`services.optimizer.reprojection`); the camera jumps to the best pose not yet visited. At
the best pose the continuous (θ, φ) is refined by least-squares reprojection — also when the best
pose is another visited one than the current: a target between grid poses may look more like a
farther grid pose's view than its nearest one's (near the zenith a change of φ turns the whole
image), and the refined pose then says the current pose is the nearest; the map's prediction
there must then pair the target's detections (unpaired confidence within ``max_unmatched``), as
the current view must otherwise. An ambiguous answer is settled, while it can be, by rendering
the poses its estimate could not rule out (:mod:`.settle`).
"""

from __future__ import annotations

from dataclasses import replace

from services.optimizer.matching import compare_views
from services.optimizer.problem import Plan, SearchProblem
from services.optimizer.strategies.done import done_plan, matched_text
from services.optimizer.strategies.map_based import (
    MapEstimate,
    estimate_or_done,
    map_estimate,
    map_views,
)
from services.optimizer.strategies.moves import explore, move_between, start_plan
from services.optimizer.strategies.settle import next_check, settle, settling

__all__ = ["plan_reprojection"]


def plan_reprojection(problem: SearchProblem) -> Plan:
    """Our map-based search (module docstring)."""
    current = problem.current
    if current is None:
        return start_plan(problem)
    grid = problem.grid
    pending = settling(problem, lambda history: _done_plan(replace(problem, history=history)))
    if pending is not None and pending.answer.flat == current.flat:
        return settle(problem, pending.plan)  # back at the answer: its own plan, settled
    found = _found(problem)
    comparison = compare_views(current.observation, problem.target)
    if found is None:
        done = done_plan(problem, current, comparison, None, False)
        return done or explore(problem, current, "no object could be mapped from the views")
    est, here, done = estimate_or_done(problem, current, comparison, found)
    if done is not None:
        return settle(problem, done)
    if pending is not None:
        return next_check(problem, pending)
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
            f"({matched_text(comparison)}); trying the best unvisited pose"
        )
    return Plan(
        False, nxt, move_between(grid, current.flat, nxt), est, found.ambiguous,
        found.alternatives, why + found.note,
    )  # fmt: skip


def _found(problem: SearchProblem) -> MapEstimate | None:
    return map_estimate(
        problem, map_views(problem.history, problem.grid, problem.camera, problem.mappings)
    )


def _done_plan(problem: SearchProblem) -> Plan | None:
    """The done plan at the current pose, before it is settled (None: not done there)."""
    current, found = problem.current, _found(problem)
    if current is None or found is None:
        return None
    comparison = compare_views(current.observation, problem.target)
    return estimate_or_done(problem, current, comparison, found)[2]
