"""``paper`` — the optimised search of §3.3.

The current view mapped by the paper's eq. 2–7, latitude from the distance-to-centre profile
over every candidate camera height, longitude from the rotation solve
(:mod:`services.optimizer.layout`), then a jump to the grid pose nearest the estimate. If the
estimate points at the current pose but the views differ, it steps to the neighbour nearest the
continuous estimate. The layout estimate is ambiguous when fewer than two objects match or they
disagree on the rotation.
"""

from __future__ import annotations

import math

import numpy as np

from services.common.geometry.sphere import angular_distance_deg
from services.optimizer.geometry import PinholeCameras
from services.optimizer.layout import LayoutEstimate, estimate_layout
from services.optimizer.matching import compare_views
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit
from services.optimizer.strategies.done import done_plan, matched_text
from services.optimizer.strategies.moves import explore, move_between, start_plan

__all__ = ["CalibrationMissingError", "decision_key", "plan_paper"]


class CalibrationMissingError(ValueError):
    """The strategy needs the paper mapping's coefficients and none are stored for the camera."""


def decision_key(problem: SearchProblem) -> int | None:
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
        return start_plan(problem)
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    layout = _layout(problem, current)
    est = _layout_estimate(problem, layout) if layout.ok else None
    here = est is not None and est.flat == current.flat
    done = done_plan(problem, current, comparison, est, here, ambiguous=layout.ambiguous)
    if done is not None:
        return done
    if est is None:
        return explore(problem, current, f"cannot estimate the target: {layout.reason}")
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
        f"the estimate points here but the views differ ({matched_text(comparison)}); "
        "trying the neighbour nearest the continuous estimate" + note,
    )  # fmt: skip
