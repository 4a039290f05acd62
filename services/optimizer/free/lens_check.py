"""The lens check of a dense fit (:mod:`.dense`): whether the target's edges bend as a
distorting lens's, which a pinhole's fit cannot follow.

From where the pinhole fit ended, the pose, OpenCV's radial ``k1`` (``x_d = x (1 + k1 r²)``,
``r`` the normalised radius) and, unless it was given, the focal length are fitted once more at
full resolution (``cv2.projectPoints``, whose Jacobian has the ``k1`` column:
:class:`~.chamfer.ChamferProblem` with ``fit_radial``). How far that ``k1`` moves the farthest
explained edge points, ``f |k1| r³``, and how surely (its standard deviation), tell a distorted
photo from a pinhole's; :mod:`services.optimizer.lens_pose` judges it. So does the share of
the pinhole fit's misfit that the lens explains, ``1 − C(k1 fit) / C(pinhole)`` with ``C`` the
full-resolution level's soft-L1 cost (:func:`~.level_fit.level_cost`). A fit made through a
radial lens that an earlier check estimated (a render through it) is checked the same way, its
``k1`` started there.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.optimizer.free.chamfer import ChamferProblem
from services.optimizer.free.edges import EdgePoints, Level
from services.optimizer.free.level_fit import (
    INLIER_PX,
    MIN_POINTS,
    RADIAL_RANGE,
    fit_level,
    level_cost,
    parameter_sigma,
)
from services.optimizer.free.refine import Intrinsics
from services.optimizer.geometry import FloatArray

__all__ = ["RadialCheck", "radial_check"]


@dataclass(frozen=True)
class RadialCheck:
    """The lens check of a fit without a given lens (:func:`radial_check`): the radial term
    ``k1`` that the edges fit with the pose and focal length, its standard deviation ``sigma``,
    how far it moves the farthest explained points from their pinhole pixels (``bend_px``, the
    95th percentile over them of ``f |k1| r³``, ``r`` the normalised radius, in film pixels)
    and how many edge points the fit explains (``inliers``); ``bounded`` when ``k1`` ended on a
    bound of :data:`RADIAL_RANGE` (the fit ran off, not a lens); the fit's world-to-camera
    ``rotation`` and ``translation`` and its ``zoom`` of the focal length; ``cost_drop``, the
    share of the pinhole fit's robust cost that the ``k1`` fit removes (None for a check started
    through a lens, which has no pinhole fit to compare with)."""

    k1: float
    sigma: float
    bend_px: float
    inliers: int
    bounded: bool
    rotation: FloatArray
    translation: FloatArray
    zoom: float
    cost_drop: float | None = None

    @property
    def position(self) -> FloatArray:
        """The camera centre ``c = -Rᵀ t`` (scene units)."""
        centre: FloatArray = -self.rotation.T @ self.translation
        return centre


def radial_check(
    points: EdgePoints,
    level: Level,
    k: Intrinsics,
    x: FloatArray,
    pixel: float,
    fit_focal: bool,
    k1: float = 0.0,
) -> RadialCheck | None:
    """Whether the target's edges bend as a lens would: the pose, OpenCV's radial ``k1``
    (``x_d = x (1 + k1 r²)``) and, with ``fit_focal``, the focal length fitted at the
    full-resolution ``level`` from the fit ``x`` (pose and zoom) made through the radial lens
    ``k1`` (0: a pinhole's), a point explained within :data:`INLIER_PX` of the target's pixels
    (``pixel`` film pixels each). None when fewer than :data:`MIN_POINTS` points are explained
    there."""
    problem = ChamferProblem(points, level, k, None, fit_focal=fit_focal, fit_radial=True)
    start = x if fit_focal else x[:6]
    y = fit_level(problem, np.append(start, k1))
    radius = INLIER_PX * pixel
    distances = problem.residuals(y)
    explained = distances <= radius
    if explained.sum() < MIN_POINTS:
        return None
    index = problem.radial_index
    sigma = parameter_sigma(problem, y, radius, index=index)
    rotation, _ = cv2.Rodrigues(y[:3])
    camera = points.world @ rotation.T + y[3:6]
    normalised = np.hypot(camera[:, 0], camera[:, 1]) / np.maximum(camera[:, 2], 1e-9)
    reach = float(np.percentile(normalised[explained], 95))
    fitted = float(y[index])
    zoom = float(y[6]) if fit_focal else float(x[6])
    drop = None
    if k1 == 0.0:  # from the pinhole fit itself: its cost against the lens fit's
        pinhole = level_cost(problem.residuals(np.append(start, 0.0)), level.sigma)
        drop = 1.0 - level_cost(distances, level.sigma) / pinhole if pinhole > 0.0 else 0.0
    return RadialCheck(
        k1=fitted,
        sigma=sigma,
        bend_px=k.fx * zoom * abs(fitted) * reach**3,
        inliers=int(explained.sum()),
        bounded=min(abs(fitted - bound) for bound in RADIAL_RANGE) < 1e-3,
        rotation=np.asarray(rotation, dtype=np.float64),
        translation=np.asarray(y[3:6], dtype=np.float64),
        zoom=zoom,
        cost_drop=drop,
    )
