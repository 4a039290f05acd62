"""The refinement's batched finite differences: the Jacobian least_squares would estimate."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize._numdiff import approx_derivative

from services.optimizer.reprojection import _DIFF_STEP, _forward_steps

LOWER = np.array([7.5, -np.inf])
UPPER = np.array([82.5, np.inf])


def residuals(x: np.ndarray) -> np.ndarray:
    return np.array([np.sin(x[0]) * x[1], x[0] ** 2 - x[1], np.exp(x[1] / 400.0) * x[0]])


@settings(max_examples=200, deadline=None)
@given(
    theta=st.one_of(st.floats(7.5, 82.5), st.sampled_from([7.5, 82.5, 82.5 - 1e-9])),
    phi=st.one_of(st.floats(-720.0, 720.0), st.sampled_from([0.0, -0.0, 360.0])),
)
def test_forward_steps_give_scipys_two_point_jacobian_to_the_last_bit(theta, phi):
    """refine_pose predicts the perturbed poses in one batch instead of letting the solver
    difference its residuals; its answers stay those of the solver's own differences."""
    x = np.array([theta, phi])
    expected = approx_derivative(
        residuals, x, method="2-point", rel_step=_DIFF_STEP, bounds=(LOWER, UPPER)
    )
    h = _forward_steps(x, LOWER, UPPER)
    shifted = np.array([residuals(p) for p in x + np.diag(h)])
    mine = ((shifted - residuals(x)) / ((x + h) - x)[:, np.newaxis]).T
    assert np.all((x + h >= LOWER) & (x + h <= UPPER))
    np.testing.assert_array_equal(mine, expected)
