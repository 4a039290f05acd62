"""Next-best-pose strategies (paper §3.3 and ours): ``simple``, ``paper`` and ``reprojection``.

Every strategy is a pure function of a :class:`~services.optimizer.problem.SearchProblem` — the
grid, the camera, the target's detections and the visited poses with theirs — to a
:class:`~services.optimizer.problem.Plan`. Each has its module (:mod:`.simple`, :mod:`.paper`,
:mod:`.reprojection`); all apply one done test (:mod:`.done`, with its tolerance derivation);
the map-based two share :mod:`.map_based`, and all make the moves of :mod:`.moves`. This module
is the registry.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Final

from services.common.contracts.optimize import StrategyName
from services.optimizer.problem import Plan, SearchProblem
from services.optimizer.strategies import paper, simple
from services.optimizer.strategies.done import LOOSE_FACTOR, NOISE_SIGMAS, loose_tolerance
from services.optimizer.strategies.paper import CalibrationMissingError
from services.optimizer.strategies.reprojection import plan_reprojection

__all__ = [
    "DEFAULT_STRATEGY",
    "LOOSE_FACTOR",
    "NOISE_SIGMAS",
    "STRATEGIES",
    "CalibrationMissingError",
    "StrategySpec",
    "loose_tolerance",
    "plan_next",
]

DEFAULT_STRATEGY: Final[StrategyName] = "reprojection"


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


STRATEGIES: Final[dict[str, StrategySpec]] = {
    "simple": StrategySpec(
        "simple",
        "The paper's step-by-step baseline (Fig. 6a): one N/S/E/W move per iteration, "
        "latitude first, then longitude the shorter way, towards the pose whose projected "
        "layout of the current view best matches the target.",
        simple.plan_simple,
        needs_calibration=False,
        decision_key=simple.decision_key,
    ),
    "paper": StrategySpec(
        "paper",
        "The paper's optimised search (§3.3): latitude from the distance-to-centre profile, "
        "longitude from the rotation solve (paper mapping, eq. 2-8), jump to the nearest grid "
        "pose.",
        paper.plan_paper,
        needs_calibration=True,
        decision_key=paper.decision_key,
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
