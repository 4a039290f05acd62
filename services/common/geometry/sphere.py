"""Poses on the sphere about the origin: camera positions of (θ, φ) and back, and the angle
between two poses' view directions.

Conventions (all angles in degrees)
-----------------------------------
A pose is ``(θ, φ)``: θ is the polar angle from the zenith +z, φ the azimuth from +x,
counter-clockwise seen from above, in [0, 360). A camera at distance ``r`` from the origin sits at

.. math:: \\mathbf{c}(θ, φ, r) = r\\,(\\sin θ \\cos φ,\\ \\sin θ \\sin φ,\\ \\cos θ)

and looks at the origin, so its view direction is :math:`-\\mathbf{c}/r`. At the pole (θ = 0)
every φ gives the same position and view direction; φ = 0 stands for all of them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.geometry.pose import Pose

__all__ = ["angular_distance_deg", "cartesian_to_pose", "pose_to_cartesian"]


def pose_to_cartesian(
    theta_deg: ArrayLike, phi_deg: ArrayLike, radius: ArrayLike = 1.0
) -> NDArray[np.float64]:
    """Camera positions of poses on a sphere about the origin (eq. 1).

    .. math:: \\mathbf{c} = r\\,(\\sin θ \\cos φ,\\ \\sin θ \\sin φ,\\ \\cos θ)

    Parameters
    ----------
    theta_deg, phi_deg : array_like
        Polar angle from +z and azimuth from +x (counter-clockwise), in degrees.
    radius : array_like, optional
        Distance r from the origin, in world units.

    Returns
    -------
    ndarray, shape (..., 3)
        Positions, broadcast over the three inputs.
    """
    theta = np.radians(np.asarray(theta_deg, dtype=np.float64))
    phi = np.radians(np.asarray(phi_deg, dtype=np.float64))
    r = np.asarray(radius, dtype=np.float64)
    sin_theta = np.sin(theta)
    xyz = np.stack(
        np.broadcast_arrays(sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)),
        axis=-1,
    )
    result: NDArray[np.float64] = xyz * r[..., np.newaxis]
    return result


def cartesian_to_pose(
    xyz: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Pose angles and radius of camera positions; the inverse of :func:`pose_to_cartesian`.

    .. math:: r = \\lVert \\mathbf{c} \\rVert,\\quad
              θ = \\operatorname{atan2}(\\sqrt{x^2 + y^2},\\ z),\\quad
              φ = \\operatorname{atan2}(y,\\ x) \\bmod 360

    Parameters
    ----------
    xyz : array_like, shape (..., 3)
        Positions in world units.

    Returns
    -------
    theta_deg : ndarray, shape (...)
        Polar angle in [0, 180] degrees (above 90 below the horizon).
    phi_deg : ndarray, shape (...)
        Azimuth in [0, 360) degrees; 0 on the z axis (θ = 0 or 180, or the origin).
    radius : ndarray, shape (...)
        Distance from the origin.
    """
    points = np.asarray(xyz, dtype=np.float64)
    if points.shape[-1:] != (3,):
        raise ValueError(f"xyz must have shape (..., 3), got {points.shape}")
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    rho = np.hypot(x, y)
    theta_deg = np.degrees(np.arctan2(rho, z))
    # atan2(±0, -0) is ±180, and a tiny negative angle mod 360 rounds to 360.0: pin both.
    phi_deg = np.mod(np.degrees(np.arctan2(y, x)), 360.0)
    phi_deg = np.where((rho == 0.0) | (phi_deg >= 360.0), 0.0, phi_deg)
    return theta_deg, phi_deg, np.hypot(rho, z)


def _direction(pose: Pose | tuple[ArrayLike, ArrayLike]) -> NDArray[np.float64]:
    if isinstance(pose, Pose):
        return pose_to_cartesian(pose.theta_deg, pose.phi_deg)
    theta_deg, phi_deg = pose
    return pose_to_cartesian(theta_deg, phi_deg)


def angular_distance_deg(
    pose_a: Pose | tuple[ArrayLike, ArrayLike], pose_b: Pose | tuple[ArrayLike, ArrayLike]
) -> NDArray[np.float64]:
    """Great-circle angle between the view directions of two poses, in degrees.

    Both cameras look at the origin, so the angle between view directions is the angle between
    the unit position vectors **a**, **b**, computed as

    .. math:: α = \\operatorname{atan2}(\\lVert \\mathbf{a} \\times \\mathbf{b} \\rVert,\\
              \\mathbf{a} \\cdot \\mathbf{b}) \\in [0, 180]

    which, unlike arccos of the dot product, stays accurate for nearly equal directions.

    Parameters
    ----------
    pose_a, pose_b : Pose or (theta_deg, phi_deg)
        A pose model or a pair of broadcastable angle arrays in degrees.

    Returns
    -------
    ndarray
        The angles, broadcast over the inputs (0-d for two single poses).
    """
    a = _direction(pose_a)
    b = _direction(pose_b)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    angle: NDArray[np.float64] = np.degrees(np.arctan2(cross, dot))
    return angle
