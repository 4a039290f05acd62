"""The dense fit's cost (:mod:`.dense`): the oriented chamfer residuals of the model's edge
points against one level of the target's distance maps, and their Jacobian.

For a pose ``p`` (rotation vector ``ω``, translation ``t`` and, with the focal length fitted,
a zoom ``s``, and with a radial term fitted too, OpenCV's ``k1``), point ``X_i`` projects to
``π(X_i; p)`` and its residual is the level's distance map of its orientation bin there,
``D_{b_i}(π(X_i; p))``, sampled bilinearly; the Jacobian is ``∇D · ∂π/∂p``.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.geometry.free_camera import LensDistortion
from services.optimizer.free.edges import (
    EdgePoints,
    Level,
    bilinear,
    bilinear_corners,
    lens_coefficients,
)
from services.optimizer.free.refine import Intrinsics
from services.optimizer.geometry import FloatArray

__all__ = ["ChamferProblem"]


class ChamferProblem:
    """The chamfer residuals and their Jacobian at one level (module docstring), on ``points``
    (or the evenly spaced ``limit`` of them).

    Without lens distortion the pinhole projection and its Jacobian are computed here in numpy
    (``cv2.projectPoints`` always computes its 15-column Jacobian, ~17 times the cost of the
    projection alone, also for the residual evaluations that need none); the last pose's
    projection is kept, as ``least_squares`` asks for the Jacobian at the pose it has just
    evaluated.
    """

    def __init__(
        self,
        points: EdgePoints,
        level: Level,
        intrinsics: Intrinsics,
        distortion: LensDistortion | None,
        fit_focal: bool,
        limit: int | None = None,
        fit_radial: bool = False,
    ) -> None:
        world, bins = points.world, points.bins
        if limit is not None and len(world) > limit:
            keep = np.linspace(0, len(world) - 1, limit).round().astype(np.intp)
            world, bins = world[keep], bins[keep]
        self.world, self.bins, self.level, self.k = world, bins, level, intrinsics
        self.coefficients = lens_coefficients(distortion)
        if fit_radial and np.any(self.coefficients):
            raise ValueError("a radial term is fitted on a pinhole lens only")
        self.pinhole = not np.any(self.coefficients) and not fit_radial
        self.fit_focal, self.fit_radial = fit_focal, fit_radial
        self.radial_index = 7 if fit_focal else 6
        """Where ``k1`` lies in the parameters, when fitted: after the zoom, if any."""
        self._at: FloatArray | None = None
        self._uv: FloatArray = np.empty((0, 2))
        self._ahead: NDArray[np.bool_] = np.empty(0, dtype=bool)
        self._camera: FloatArray = np.empty((0, 3))
        self._columns: FloatArray | None = None

    def _focal(self, x: FloatArray) -> tuple[float, float]:
        """The level's focal lengths at ``x`` (pixels of the level)."""
        scale = float(x[6]) if self.fit_focal else 1.0
        return self.k.fx * scale / self.level.scale, self.k.fy * scale / self.level.scale

    def _project(self, x: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The points' pixels at ``x`` and which lie in front of the camera (cached)."""
        if self._at is not None and np.array_equal(x, self._at):
            return self._uv, self._ahead
        self._at, self._columns = x.copy(), None
        rotation, _ = cv2.Rodrigues(x[:3])
        camera = self.world @ rotation.T + x[3:6]
        self._camera, self._ahead = camera, camera[:, 2] > 1e-6
        fx, fy = self._focal(x)
        cx, cy = self.k.cx / self.level.scale, self.k.cy / self.level.scale
        if self.pinhole:
            inverse = 1.0 / np.where(self._ahead, camera[:, 2], 1.0)
            self._uv = np.stack(
                [fx * camera[:, 0] * inverse + cx, fy * camera[:, 1] * inverse + cy], axis=1
            )
        else:
            matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            lens = self.coefficients
            if self.fit_radial:
                lens = np.array([float(x[self.radial_index]), 0.0, 0.0, 0.0, 0.0])
            uv, jacobian = cv2.projectPoints(self.world, x[:3], x[3:6], matrix, lens)
            self._uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
            self._columns = self._opencv_columns(np.asarray(jacobian), fx, fy, x)
        return self._uv, self._ahead

    def _opencv_columns(
        self, jacobian: FloatArray, fx: float, fy: float, x: FloatArray
    ) -> FloatArray:
        """``∂(u, v)/∂p`` ``(N, 2, P)`` from ``cv2.projectPoints``' Jacobian (its columns: the
        rotation, translation, ``fx, fy, cx, cy``, then ``k1``…)."""
        columns = jacobian[:, :6]
        if self.fit_focal:
            focal = (jacobian[:, 6:7] * fx + jacobian[:, 7:8] * fy) / float(x[6])
            columns = np.hstack([columns, focal])
        if self.fit_radial:
            columns = np.hstack([columns, jacobian[:, 10:11]])
        return columns.reshape(-1, 2, columns.shape[1])

    def _pinhole_columns(self, x: FloatArray) -> FloatArray:
        """``∂(u, v)/∂p`` ``(N, 2, P)`` of the pinhole projection ``u = f_x X_c/Z_c + c_x``:
        ``∂u/∂X_c = (f_x/Z_c)(1, 0, -X_c/Z_c)`` (likewise ``v``), ``∂X_c/∂t = I``,
        ``∂X_c/∂ω = (∂R/∂ω) X`` (``cv2.Rodrigues``' Jacobian) and ``∂u/∂s = (u - c_x)/s``."""
        camera, ahead = self._camera, self._ahead
        _, d_rotation = cv2.Rodrigues(x[:3])  # (3, 9): ∂R_ij/∂ω_k at [k, 3i + j]
        # ∂X_c,i/∂ω_k = Σ_j ∂R_ij/∂ω_k X_j, as (N, 3 i, 3 k)
        d_camera = self.world @ d_rotation.reshape(3, 3, 3).transpose(2, 1, 0).reshape(3, 9)
        d_camera = d_camera.reshape(-1, 3, 3)
        inverse = 1.0 / np.where(ahead, camera[:, 2], 1.0)
        fx, fy = self._focal(x)
        x_n, y_n = camera[:, 0] * inverse, camera[:, 1] * inverse
        count = 7 if self.fit_focal else 6
        columns = np.zeros((len(camera), 2, count))
        # ∂u/∂t = (f_x/Z)(1, 0, -x), ∂v/∂t = (f_y/Z)(0, 1, -y)
        columns[:, 0, 3] = fx * inverse
        columns[:, 0, 5] = -fx * inverse * x_n
        columns[:, 1, 4] = fy * inverse
        columns[:, 1, 5] = -fy * inverse * y_n
        columns[:, :, :3] = np.einsum("nai,nik->nak", columns[:, :, 3:6], d_camera)
        if self.fit_focal:
            scale = float(x[6])
            columns[:, 0, 6] = fx * x_n / scale
            columns[:, 1, 6] = fy * y_n / scale
        return columns

    def residuals(self, x: FloatArray) -> FloatArray:
        uv, ahead = self._project(x)
        corners, weights, inside = bilinear_corners(self.level, self.bins, uv)
        d = np.where(inside, bilinear(self.level.distance, corners, weights), self.level.cap)
        result: FloatArray = np.where(ahead, d, self.level.cap)
        return result

    def jacobian(self, x: FloatArray) -> FloatArray:
        uv, ahead = self._project(x)
        if self._columns is None:
            self._columns = self._pinhole_columns(x)
        corners, weights, inside = bilinear_corners(self.level, self.bins, uv)
        keep = inside & ahead
        gx = np.where(keep, bilinear(self.level.grad_x, corners, weights), 0.0)
        gy = np.where(keep, bilinear(self.level.grad_y, corners, weights), 0.0)
        result: FloatArray = gx[:, None] * self._columns[:, 0] + gy[:, None] * self._columns[:, 1]
        return result
