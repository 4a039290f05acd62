"""A camera pose as the free bench compares them: camera-to-world rotation, centre, fov."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.geometry.camera import PinholeCamera, fov_deg_of
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera

__all__ = ["Estimate", "intrinsics_matrix"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Estimate:
    """A camera: ``rotation`` R_cw (3x3, columns right, down, forward in world axes),
    ``position`` its centre (scene units), ``fov_deg`` its horizontal field of view."""

    rotation: FloatArray
    position: FloatArray
    fov_deg: float

    @property
    def world_to_camera(self) -> tuple[FloatArray, FloatArray]:
        """OpenCV's ``R = R_cwᵀ`` and ``t = -R c``."""
        rotation = self.rotation.T
        return rotation, -rotation @ self.position

    @classmethod
    def of_camera(cls, camera: FreeCamera, default_fov_deg: float, width: int) -> Estimate:
        """The estimate that is exactly ``camera`` (its fov on a ``width``-pixel film)."""
        pinhole = free_pinhole_camera(camera, width, width, default_fov_deg)
        return cls(
            camera.rotation(), np.asarray(camera.position, dtype=np.float64), pinhole.fov_deg
        )

    @classmethod
    def of_world_to_camera(
        cls, rotation: FloatArray, translation: FloatArray, fov_deg: float
    ) -> Estimate:
        """The estimate of OpenCV's ``R``, ``t`` (world to camera)."""
        return cls(rotation.T.copy(), -rotation.T @ translation, fov_deg)


def intrinsics_matrix(camera: PinholeCamera) -> FloatArray:
    """OpenCV's 3x3 camera matrix ``K`` of ``camera``."""
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def fov_of_focal(fx: float, width: int) -> float:
    """The horizontal fov in degrees of focal length ``fx`` px on a ``width``-pixel film."""
    return fov_deg_of(fx, width)
