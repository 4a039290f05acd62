"""The refinement's Jacobian: what :func:`refine_pose` hands the solver is the derivative of its own
residuals, checked against central differences of those residuals (numpy, no solver code)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from services.common.geometry.pose import GridIndex
from services.optimizer import reprojection
from services.optimizer.problem import SearchProblem, Visit
from services.optimizer.strategies import plan_next
from simulation import SceneSimulator

Function = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SolverCall:
    """What refine_pose gave :func:`scipy.optimize.least_squares`, and the pose it found."""

    residuals: Function
    jacobian: Function
    start: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    found: np.ndarray


@pytest.fixture(scope="module")
def solver_call(catalog) -> SolverCall:
    """The last refinement of a reprojection search on the demo scene for a target between grid
    poses (so the refinement has something to do), with the solver call recorded."""
    calls: list[SolverCall] = []
    solve = reprojection.least_squares

    def recorded(fun: Function, x0: np.ndarray, *, jac: Function, bounds: Any, **kw: Any) -> Any:
        result = solve(fun, x0, jac=jac, bounds=bounds, **kw)
        lower, upper = (np.asarray(b, dtype=float) for b in bounds)
        calls.append(SolverCall(fun, jac, np.array(x0), lower, upper, result.x))
        return result

    scene = catalog.get("demo")
    grid = scene.spec.search.grid()
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.grid_views(grid)
    target = simulator.observe(simulator.views([33.7], [47.9]), 0)
    history = [grid.flat(GridIndex(lat=8, lon=30))]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(reprojection, "least_squares", recorded)
        for _ in range(10):
            visits = tuple(
                Visit(
                    f, float(grid.theta_deg[f]), float(grid.phi_deg[f]), simulator.observe(views, f)
                )
                for f in history
            )
            plan = plan_next(SearchProblem(grid, scene.spec.camera, target, visits), "reprojection")
            if plan.done:
                break
            history.append(plan.next_flat)
    assert calls, "the search never refined a pose"
    return calls[-1]


def central_difference(residuals: Function, x: np.ndarray, h_deg: float = 1e-3) -> np.ndarray:
    """``∂r/∂x`` ``(m, 2)`` in pixels per degree: ``(r(x + h e_i) − r(x − h e_i)) / 2h``."""
    columns = []
    for i in range(len(x)):
        step = np.zeros_like(x)
        step[i] = h_deg
        columns.append((residuals(x + step) - residuals(x - step)) / (2 * h_deg))
    return np.stack(columns, axis=1)


def test_the_jacobian_is_the_derivative_of_the_residuals(solver_call):
    call = solver_call
    for x in (call.start, call.found, call.found + np.array([1.5, -2.0])):
        jacobian = call.jacobian(x)
        expected = central_difference(call.residuals, x)
        assert jacobian.shape == (len(call.residuals(x)), 2)
        assert np.abs(expected).max() > 1.0  # boxes move by pixels per degree: a real test
        np.testing.assert_allclose(jacobian, expected, rtol=1e-3, atol=1e-3)


def test_at_the_theta_bound_the_difference_steps_back_inside(solver_call):
    """At the upper θ bound a forward step would leave the bounds: it is taken backwards, and the
    Jacobian is still the residuals' derivative."""
    call = solver_call
    x = np.array([call.upper[0], call.found[1] % 360.0])
    steps = reprojection._forward_steps(x, call.lower, call.upper)
    assert steps[0] < 0 < steps[1]
    assert np.all((x + steps >= call.lower) & (x + steps <= call.upper))
    np.testing.assert_allclose(
        call.jacobian(x), central_difference(call.residuals, x), rtol=1e-3, atol=1e-3
    )
