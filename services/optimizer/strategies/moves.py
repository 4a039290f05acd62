"""Grid moves every strategy makes: the start pose, steps to neighbours, and where to go when
nothing can be estimated."""

from __future__ import annotations

import numpy as np

from services.common.geometry.grid import Direction, HemisphereGrid
from services.common.geometry.pose import GridIndex
from services.optimizer.problem import Move, Plan, SearchProblem, Visit

__all__ = ["default_start", "explore", "move_between", "neighbour_flat", "start_plan"]


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


def neighbour_flat(grid: HemisphereGrid, flat: int, direction: Direction) -> int | None:
    neighbour = grid.neighbour(grid.unflat(flat), direction)
    return None if neighbour is None else grid.flat(neighbour)


def _ring_of(grid: HemisphereGrid, theta_deg: float) -> int:
    rings = np.array([ring.theta_deg for ring in grid.rings])
    return int(np.argmin(np.abs(rings - theta_deg)))


def explore(problem: SearchProblem, current: Visit, why: str) -> Plan:
    """A fallback move when nothing can be estimated: towards the zenith (views there map best),
    else around the ring, else away from the zenith."""
    directions: tuple[Direction, ...] = ("N", "E", "S")
    for direction in directions:
        nxt = neighbour_flat(problem.grid, current.flat, direction)
        if nxt is not None:
            return Plan(False, nxt, direction, None, True, (), why)
    return Plan(False, current.flat, "stay", None, True, (), why)


def start_plan(problem: SearchProblem) -> Plan:
    return Plan(
        done=False,
        next_flat=default_start(problem.grid),
        move="start",
        estimate=None,
        ambiguous=False,
        alternatives=(),
        reason="no view yet: render this start pose and send its detections in the history",
    )
