"""The pinhole camera on the hemisphere: its axes, intrinsics, extrinsics and projection.

Conventions (OpenCV): camera axes x right, y down, z forward; pixel (0, 0) is the top-left corner
of the top-left pixel. The renderer builds Mitsuba's sensor transform from the same axes
(:func:`mitsuba_to_world`), so projection here and the rendered image agree by construction; the
tests check it against the renderer's own per-pixel object ids.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from services.common.base import FrozenModel
from services.common.geometry.pose import Pose

__all__ = [
    "PinholeCamera",
    "camera_axes",
    "film_camera",
    "pinhole_camera",
    "focal_length_px",
    "fov_deg_of",
    "mitsuba_to_world",
    "pixel_rays",
    "project",
]

FloatArray = NDArray[np.float64]


class PinholeCamera(FrozenModel):
    """Pinhole intrinsics and world-to-camera extrinsics in the OpenCV convention.

    Camera axes: x right, y down, z forward. A world point X maps to pixel coordinates
    ``K @ (R @ X + t)`` after division by depth, with pixel (0, 0) the top-left corner of the
    top-left pixel (so the centre of that pixel is (0.5, 0.5)).
    """

    width: int
    height: int
    fov_deg: float = Field(description="Horizontal field of view in degrees.")
    fx: float
    fy: float
    cx: float
    cy: float
    rotation: tuple[tuple[float, float, float], ...] = Field(
        description="3x3 world-to-camera rotation R, row-major."
    )
    translation: tuple[float, float, float] = Field(description="World-to-camera translation t.")
    position: tuple[float, float, float] = Field(description="Camera centre in world units.")


def camera_axes(
    theta_deg: ArrayLike, phi_deg: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """World directions of the camera's right, down and forward axes for poses (θ, φ) in degrees.

    The camera at ``c = r (sinθ cosφ, sinθ sinφ, cosθ)`` looks at the origin, so its forward axis is
    ``f = -c / r``. Image-up is world +z with its component along ``f`` removed::

        u ∝ ẑ - (ẑ·f) f = ẑ + cosθ f = sinθ (-cosθ cosφ, -cosθ sinφ, sinθ)
        u = (-cosθ cosφ, -cosθ sinφ, sinθ)

    The last form is already unit length and stays defined at the pole θ = 0, where it is the limit
    of the ring poses (-cosφ, -sinφ, 0): the pole view is oriented by φ like its neighbours. Then
    ``down = -u`` and ``right = down × forward = f × u`` (x right, y down, z forward: right-handed).

    Returns three arrays of shape ``broadcast(θ, φ).shape + (3,)``.
    """
    theta = np.radians(np.asarray(theta_deg, dtype=np.float64))
    phi = np.radians(np.asarray(phi_deg, dtype=np.float64))
    theta, phi = np.broadcast_arrays(theta, phi)
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    fx, fy, fz = -(st * cp), -(st * sp), -ct
    ux, uy, uz = -ct * cp, -ct * sp, st
    forward = np.stack([fx, fy, fz], axis=-1)
    up = np.stack([ux, uy, uz], axis=-1)
    # f × u written out (np.cross's own order of operations, without its wrapper's cost: the
    # optimizer builds cameras for a few poses at a time, many times per request).
    right = np.stack([fy * uz - fz * uy, fz * ux - fx * uz, fx * uy - fy * ux], axis=-1)
    return right, -up, forward


def focal_length_px(fov_deg: float, width: float) -> float:
    """Focal length in pixels for a horizontal field of view: ``f = (W / 2) / tan(fov / 2)``."""
    return (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)


def fov_deg_of(focal_px: float, width: float) -> float:
    """The horizontal field of view of a focal length in pixels (:func:`focal_length_px`'s
    inverse): ``fov = 2 atan(W / (2 f))``."""
    return math.degrees(2.0 * math.atan(width / (2.0 * focal_px)))


def film_camera(
    width: int, height: int, focal: tuple[float, float], centre: tuple[float, float]
) -> PinholeCamera:
    """A camera of intrinsics alone (``focal`` = (fx, fy), ``centre`` = (cx, cy) pixels on a
    ``width`` x ``height`` film) at the origin, looking along +z: for checks on the film alone
    (whether a lens folds it)."""
    return PinholeCamera(
        width=width,
        height=height,
        fov_deg=fov_deg_of(focal[0], width),
        fx=focal[0],
        fy=focal[1],
        cx=centre[0],
        cy=centre[1],
        rotation=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        translation=(0.0, 0.0, 0.0),
        position=(0.0, 0.0, 0.0),
    )


def pinhole_camera(
    pose: Pose, radius: float, fov_deg: float, width: int, height: int
) -> PinholeCamera:
    """Intrinsics and world-to-camera extrinsics of the hemisphere camera at ``pose``.

    Square pixels (``fy = fx``) and the principal point at the image centre, as Mitsuba's
    ``perspective`` sensor with ``fov_axis = x``.
    """
    right, down, forward = camera_axes(pose.theta_deg, pose.phi_deg)
    rotation = np.stack([right, down, forward])
    position = -forward * radius
    translation = -rotation @ position
    f = focal_length_px(fov_deg, width)
    return PinholeCamera(
        width=width,
        height=height,
        fov_deg=fov_deg,
        fx=f,
        fy=f,
        cx=width / 2.0,
        cy=height / 2.0,
        rotation=tuple(tuple(float(v) for v in row) for row in rotation),
        translation=(float(translation[0]), float(translation[1]), float(translation[2])),
        position=(float(position[0]), float(position[1]), float(position[2])),
    )


def project(points: ArrayLike, camera: PinholeCamera) -> tuple[FloatArray, FloatArray]:
    """Project world points ``(..., 3)`` to pixels ``(..., 2)``; also return their depth (z_cam).

    ``u = fx · x_c / z_c + cx``, ``v = fy · y_c / z_c + cy`` with ``X_c = R X + t``. Points behind
    the camera (depth <= 0) get NaN pixels.
    """
    pts = np.asarray(points, dtype=np.float64)
    rotation = np.asarray(camera.rotation)
    cam = pts @ rotation.T + np.asarray(camera.translation)
    depth = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.fx * cam[..., 0] / depth + camera.cx
        v = camera.fy * cam[..., 1] / depth + camera.cy
    pixels = np.stack([u, v], axis=-1)
    pixels[depth <= 0] = np.nan
    return pixels, depth


def pixel_rays(pixels: ArrayLike, camera: PinholeCamera) -> FloatArray:
    """Unit world directions of the rays through pixel coordinates ``(..., 2)`` (inverse of
    :func:`project` up to depth); every ray starts at ``camera.position``."""
    px = np.asarray(pixels, dtype=np.float64)
    x = (px[..., 0] - camera.cx) / camera.fx
    y = (px[..., 1] - camera.cy) / camera.fy
    cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    world = cam @ np.asarray(camera.rotation)
    norm: FloatArray = world / np.linalg.norm(world, axis=-1, keepdims=True)
    return norm


def mitsuba_to_world(pose: Pose, radius: float) -> FloatArray:
    """The 4x4 camera-to-world matrix of Mitsuba's sensor for ``pose``.

    Mitsuba's camera space is x left, y up, z forward (what its ``look_at`` builds), so the columns
    are ``(-right, -down, forward, position)``.
    """
    right, down, forward = camera_axes(pose.theta_deg, pose.phi_deg)
    matrix = np.eye(4)
    matrix[:3, 0] = -right
    matrix[:3, 1] = -down
    matrix[:3, 2] = forward
    matrix[:3, 3] = -forward * radius
    return matrix
