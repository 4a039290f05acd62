"""Vectorised hemisphere cameras and the camera-relative ground frame (paper eq. 7).

The camera model is the project's one pinhole model (:mod:`services.common.geometry.camera`): axes
from
:func:`~services.common.geometry.camera.camera_axes`, square pixels with focal length
``f = (W/2) / tan(fov/2)``, principal point at the image centre, pixel (0, 0) the top-left corner
of the top-left pixel. :class:`PinholeCameras` holds it for many poses at once so strategies can
project a whole map into every grid pose with one ``einsum``.

Camera-relative ground frame
----------------------------
For a camera at azimuth φ the ground plane gets two axes through the scene centre,

.. math:: \\mathbf{e}_1 = (\\cos φ, \\sin φ), \\qquad \\mathbf{e}_2 = (-\\sin φ, \\cos φ),

``e1`` pointing from the centre towards the camera's foot and ``e2`` along the image's right
axis (the camera's right vector is horizontal,
:func:`~services.common.geometry.camera.camera_axes`). A
ground point with camera-relative offsets ``q = (q1, q2)`` sits at

.. math:: \\mathbf{p} = q_1 \\mathbf{e}_1 + q_2 \\mathbf{e}_2 = R(φ)\\,\\mathbf{q}

with ``R(φ)`` the 2-D rotation by φ: this is the paper's eq. 7, once its depth offset Δx
(measured *away* from the camera) is written as ``q1 = -Δx``. With the sign kept as in the
paper the map would be a reflection, not a rotation, and the longitude solve would not be a
rotation fit.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.geometry.camera import camera_axes, focal_length_px
from services.common.geometry.scene import CameraSpec

__all__ = [
    "PinholeCameras",
    "FloatArray",
    "ground_offsets",
    "rotate2d",
    "world_from_offsets",
]

FloatArray = NDArray[np.float64]


def rotate2d(points: ArrayLike, phi_deg: ArrayLike) -> FloatArray:
    """Rotate 2-D points ``(..., 2)`` counter-clockwise by ``phi_deg`` (broadcast): ``R(φ) p``."""
    pts = np.asarray(points, dtype=np.float64)
    phi = np.radians(np.asarray(phi_deg, dtype=np.float64))[..., np.newaxis]
    c, s = np.cos(phi)[..., 0], np.sin(phi)[..., 0]
    x, y = pts[..., 0], pts[..., 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def world_from_offsets(offsets: ArrayLike, phi_deg: ArrayLike) -> FloatArray:
    """World ground positions ``p = R(φ) q`` of camera-relative offsets ``q`` (eq. 7)."""
    return rotate2d(offsets, phi_deg)


def ground_offsets(points: ArrayLike, phi_deg: ArrayLike) -> FloatArray:
    """Camera-relative offsets ``q = R(φ)ᵀ p`` of world ground positions ``p`` ``(..., 2)``."""
    return rotate2d(points, -np.asarray(phi_deg, dtype=np.float64))


@dataclass(frozen=True)
class PinholeCameras:
    """The hemisphere camera at ``N`` poses: world-to-camera rotations and camera centres.

    Attributes
    ----------
    rotation : ndarray, shape (N, 3, 3)
        Rows are the camera's right, down and forward axes in world coordinates.
    position : ndarray, shape (N, 3)
        Camera centres ``r (sinθ cosφ, sinθ sinφ, cosθ)`` in scene units.
    focal_px, cx, cy : float
        Focal length and principal point in pixels.
    width, height : int
        Image size in pixels.
    """

    rotation: FloatArray
    position: FloatArray
    focal_px: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def at(cls, theta_deg: ArrayLike, phi_deg: ArrayLike, camera: CameraSpec) -> PinholeCameras:
        """The cameras at poses (θ, φ) in degrees (flattened, broadcast) looking at the origin."""
        theta, phi = np.broadcast_arrays(
            np.asarray(theta_deg, dtype=np.float64).ravel(),
            np.asarray(phi_deg, dtype=np.float64).ravel(),
        )
        right, down, forward = camera_axes(theta, phi)
        return cls(
            rotation=np.stack([right, down, forward], axis=-2),
            position=-forward * camera.radius,
            focal_px=focal_length_px(camera.fov_deg, camera.width),
            cx=camera.width / 2.0,
            cy=camera.height / 2.0,
            width=camera.width,
            height=camera.height,
        )

    def __len__(self) -> int:
        return int(self.position.shape[0])

    @property
    def unit_positions(self) -> FloatArray:
        """Camera centres ``(N, 3)`` on the unit sphere, ``(sinθ cosφ, sinθ sinφ, cosθ)``: minus
        the forward axes (to the last bit
        :func:`services.common.geometry.sphere.pose_to_cartesian`)."""
        units: FloatArray = -self.rotation[:, 2]
        return units

    @functools.cached_property
    def frame(self) -> tuple[FloatArray, FloatArray]:
        """``(o, e)``: camera coordinates ``(3, N)`` of the world origin, ``o = −R c``, and
        ``(3, 3, N)`` of the world's unit axes (``e[:, j]`` is axis j, i.e. column j of R), so
        that ``R (p − c) = o + Σ_j p_j e[:, j]`` elementwise (computed once per cameras)."""
        origin = -np.einsum("nij,nj->in", self.rotation, self.position)
        axes = np.ascontiguousarray(self.rotation.transpose(1, 2, 0))
        return origin, axes

    def to_camera(self, points: ArrayLike) -> FloatArray:
        """Camera coordinates ``(N, P, 3)`` of world points ``(P, 3)`` or ``(N, P, 3)``."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim == 2:
            # R (p - c) = R p - R c, with every camera's R p in one (3N x 3)(3 x P) product:
            # ~35x faster than a batched einsum over N small products (cosmos bench --profile).
            n = len(self)
            rp = (self.rotation.reshape(3 * n, 3) @ pts.T).reshape(n, 3, -1).transpose(0, 2, 1)
            rc = np.einsum("nij,nj->ni", self.rotation, self.position)
            shared: FloatArray = rp - rc[:, np.newaxis, :]
            return shared
        rel = pts - self.position[:, np.newaxis, :]
        cam: FloatArray = rel @ self.rotation.transpose(0, 2, 1)
        return cam

    def project(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Pixels ``(N, P, 2)`` and depths ``(N, P)`` of world points in every camera.

        ``u = f x_c / z_c + c_x``, ``v = f y_c / z_c + c_y``; points at or behind the camera get
        NaN pixels, as in :func:`services.common.geometry.camera.project`.
        """
        cam = self.to_camera(points)
        depth = cam[..., 2]
        safe = np.where(depth > 0.0, depth, np.nan)
        u = self.focal_px * cam[..., 0] / safe + self.cx
        v = self.focal_px * cam[..., 1] / safe + self.cy
        return np.stack([u, v], axis=-1), depth

    def normalised(self, pixels: ArrayLike) -> FloatArray:
        """Normalised image coordinates ``((u - c_x)/f, (v - c_y)/f)`` of pixels ``(..., 2)``."""
        px = np.asarray(pixels, dtype=np.float64)
        return np.stack(
            [(px[..., 0] - self.cx) / self.focal_px, (px[..., 1] - self.cy) / self.focal_px],
            axis=-1,
        )

    def directions(self, normalised: ArrayLike) -> FloatArray:
        """World directions ``Rᵀ (a, b, 1)`` (not unit length: camera depth 1) of normalised
        image coordinates ``(N, P, 2)`` or ``(P, 2)``."""
        ab = np.asarray(normalised, dtype=np.float64)
        if ab.ndim == 2:
            ab = ab[np.newaxis]
        cam = np.concatenate([ab, np.ones(ab.shape[:-1] + (1,))], axis=-1)
        world: FloatArray = np.einsum("nji,npj->npi", self.rotation, cam)
        return world
