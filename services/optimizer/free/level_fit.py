"""One level of the dense fit (:mod:`.dense`, :mod:`.lens_check`) solved: robust least squares
on a :class:`~.chamfer.ChamferProblem`, each bounded parameter within its bounds, its cost, and
a fitted parameter's standard deviation.

With ``D_i`` the residuals (the oriented chamfer distances) at the level and ``σ`` its soft-L1
scale,

.. math:: \\min_p \\sum_i ρ_σ\\big(D_i(p)^2\\big), \\qquad ρ_σ(z) = 2σ^2(\\sqrt{1 + z/σ^2} - 1)

(``scipy.optimize.least_squares``, exact trust-region steps, the problem's own Jacobian).
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np
from scipy.optimize import least_squares

from services.optimizer.free.chamfer import ChamferProblem
from services.optimizer.geometry import FloatArray

__all__ = [
    "FOCAL_RANGE",
    "INLIER_PX",
    "MAX_EVALUATIONS",
    "MIN_POINTS",
    "RADIAL_RANGE",
    "X_TOLERANCE",
    "fit_level",
    "level_cost",
    "parameter_sigma",
]

MIN_POINTS: Final = 30
"""Fewer model edge points than this do not pin six parameters: the start pose is returned."""
INLIER_PX: Final = 2.0
"""A model point within this many full-resolution pixels of a target edge is explained."""
MAX_EVALUATIONS: Final = 40
"""Residual evaluations per level."""
X_TOLERANCE: Final = 1e-6
"""``least_squares``' ``xtol``: a step below this share of the pose (well under 0.01 px on the
film) ends a level. At the default 1e-8, 157 of 180 fits on the pairs of
``benchmarks/dense_refine.py`` (focal fitted) ended by it after 29 evaluations (median), about
half of them rejected steps shrinking the trust region far below a pixel (measured with
:data:`~.dense.LEVEL_POINTS`). 1e-5 was faster still but left ``tests/optimizer/test_dense.py``'s
garden-steep fov 1.7 % off (< 1 % at 1e-6)."""
FOCAL_RANGE: Final = (0.5, 2.0)
"""The focal length's scale stays within these bounds of the start's."""
RADIAL_RANGE: Final = (-0.5, 0.5)
"""The radial term the lens check (:func:`~.lens_check.radial_check`) fits stays within these
bounds of OpenCV's ``k1`` (wide drone lenses: about −0.3…0)."""


def fit_level(problem: ChamferProblem, x: FloatArray) -> FloatArray:
    """One level's robust least squares from ``x`` (module docstring), each bounded parameter
    within its bounds."""
    lower = np.full(x.size, -np.inf)
    upper = np.full(x.size, np.inf)
    if problem.fit_focal:
        lower[6], upper[6] = FOCAL_RANGE
        x = x.copy()
        x[6] = np.clip(x[6], FOCAL_RANGE[0] + 1e-6, FOCAL_RANGE[1] - 1e-6)
    if problem.fit_radial:
        lower[problem.radial_index], upper[problem.radial_index] = RADIAL_RANGE
    result: FloatArray = least_squares(
        problem.residuals,
        x,
        jac=problem.jacobian,
        bounds=(lower, upper),
        loss="soft_l1",
        f_scale=problem.level.sigma,
        x_scale="jac",
        tr_solver="exact",
        xtol=X_TOLERANCE,
        max_nfev=MAX_EVALUATIONS,
    ).x
    return result


def level_cost(distances: FloatArray, sigma: float) -> float:
    """The full-resolution level's own robust cost: the mean of ``ρ_σ(D²)`` (soft-L1)."""
    return float(np.mean(np.sqrt(1.0 + (distances / sigma) ** 2) - 1.0))


def parameter_sigma(
    problem: ChamferProblem, x: FloatArray, radius: float = INLIER_PX, index: int = 6
) -> float:
    """The zoom's (or parameter ``index``'s) standard deviation at ``x``: ``√[(JᵀWJ)⁻¹]₇₇ s``
    with ``W`` the soft-L1 weights ``1/√(1 + D²/σ²)`` and ``s`` the RMS distance of the points
    explained (within ``radius``)."""
    distances = problem.residuals(x)
    jacobian = problem.jacobian(x)
    weights = 1.0 / np.sqrt(1.0 + (distances / problem.level.sigma) ** 2)
    explained = distances <= radius
    if explained.sum() < MIN_POINTS:
        return math.inf
    information = (jacobian * weights[:, None]).T @ jacobian
    spread = float(np.sqrt(np.mean(distances[explained] ** 2)))
    return float(np.sqrt(max(np.linalg.pinv(information)[index, index], 0.0))) * spread
