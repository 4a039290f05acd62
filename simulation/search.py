"""A simulated search: a strategy played on synthetic detections until it says it is done."""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Final

import numpy as np

from services.common.geometry.grid import HemisphereGrid
from services.optimizer.calibration import PaperCalibration
from services.optimizer.observations import Observation
from services.optimizer.problem import Plan, SearchProblem, Visit
from services.optimizer.strategies import STRATEGIES
from simulation.detections import NoiseModel, SceneSimulator

__all__ = ["SearchOutcome", "run_search"]

_MAX_REVISITS: Final = 3


@dataclass(frozen=True)
class SearchOutcome:
    """One simulated search.

    Attributes
    ----------
    target, start, final : int
        Flat grid indices of the target, the start and where the camera ended.
    arrival : int or None
        Moves after the start view until the camera first sat at the target (None: never).
    moves : int
        Moves made until the strategy declared the search done (or the move limit).
    done : bool
        Whether the strategy declared the search done.
    ambiguous : bool
        Whether any answer on the way was flagged ambiguous.
    """

    target: int
    start: int
    final: int
    arrival: int | None
    moves: int
    done: bool
    ambiguous: bool

    @property
    def success(self) -> bool:
        """Declared done with the camera at the target."""
        return self.done and self.final == self.target


def run_search(
    strategy: str,
    simulator: SceneSimulator,
    grid: HemisphereGrid,
    target: int,
    start: int,
    *,
    calibration: PaperCalibration | None = None,
    noise: NoiseModel | None = None,
    rng: np.random.Generator | None = None,
    tolerance_px: float = 1.0,
    max_moves: int = 60,
    cache: dict[Hashable, Plan] | None = None,
) -> SearchOutcome:
    """Play ``strategy`` from ``start`` towards ``target`` on simulated detections.

    ``cache`` (for strategies with a decision key, without noise) memoises plans per
    (decision key, target), exact because such a plan depends on nothing else. The
    search stops at ``max_moves`` or when a pose would be entered a fourth time (a cycle).
    """
    views = simulator.grid_views(grid)
    spec = STRATEGIES[strategy]
    if cache is not None and (spec.decision_key is None or not (noise is None or noise.clean)):
        raise ValueError("plans can be cached only for strategies with a decision key, no noise")

    clean = noise is None or noise.clean

    def observe(flat: int) -> Observation:
        if clean:
            return simulator.clean_observation(views, flat)
        return simulator.observe(views, flat, noise, rng)

    def visit(flat: int) -> Visit:
        return Visit(flat, float(grid.theta_deg[flat]), float(grid.phi_deg[flat]), observe(flat))

    target_view = observe(target)
    history = [visit(start)]
    arrival = 0 if start == target else None
    moves = 0
    ambiguous = False
    visits = {start: 1}
    while True:
        problem = SearchProblem(
            grid=grid,
            camera=simulator.camera,
            target=target_view,
            history=tuple(history),
            tolerance_px=tolerance_px,
            calibration=calibration,
        )
        key = None
        if cache is not None and spec.decision_key is not None:
            key = (spec.decision_key(problem), target)
        plan = cache.get(key) if cache is not None and key is not None else None
        if plan is None:
            plan = spec.plan(problem)
            if cache is not None and key is not None:
                cache[key] = plan
        ambiguous |= plan.ambiguous
        if plan.done or moves >= max_moves:
            break
        visits[plan.next_flat] = visits.get(plan.next_flat, 0) + 1
        if visits[plan.next_flat] > _MAX_REVISITS:
            break  # cycling: the strategy cannot make progress
        moves += 1
        history.append(visit(plan.next_flat))
        if arrival is None and plan.next_flat == target:
            arrival = moves
    return SearchOutcome(
        target=target,
        start=start,
        final=history[-1].flat,
        arrival=arrival,
        moves=moves,
        done=plan.done,
        ambiguous=ambiguous,
    )
