"""A camera anywhere: position, orientation and intrinsics, as a request gives them.

The hemisphere pose (:class:`~services.common.geometry.pose.Pose`) is a camera on a sphere looking
at the scene's centre; a :class:`FreeCamera` is any camera in the scene's world frame (z up, the
ground the plane z = 0, scene units).

Conventions
-----------
Camera axes are OpenCV's, as :class:`~services.common.geometry.camera.PinholeCamera` uses:
x right, y down, z forward (the optical axis). An orientation is given as exactly one of:

* ``quaternion_wxyz``: the unit quaternion q = (w, x, y, z) of the camera-to-world rotation
  R_cw = R(q): a vector in camera axes, rotated by q, is that vector in world axes (so R_cw's
  columns are the world directions of the camera's right, down and forward axes). Any non-zero
  length is normalised; q and -q are the same camera.
* ``yaw_deg``, ``pitch_deg`` (and ``roll_deg``): the optical axis points at yaw ψ, counter-
  clockwise about world +z from +x, and pitch ϑ below the horizontal::

      f = (cos ϑ cos ψ, cos ϑ sin ψ, -sin ϑ)

  so ϑ = 90° looks straight down (nadir) and ϑ = -90° straight up. With roll 0 the image's x axis
  is level, ``right = (sin ψ, -cos ψ, 0)``, and ``down = f × right``; at the nadir the top of the
  image then points along yaw. Roll ρ turns the camera about its optical axis, right-handed about
  f: ``right' = right cos ρ + down sin ρ``: the camera turns clockwise as seen from behind it, the
  world in the image counter-clockwise by ρ (a level camera's x axis dips by ρ).
* ``look_at`` (and ``roll_deg``): the optical axis points from ``position`` at that world point;
  the yaw and pitch follow from that direction (yaw 0 when it is vertical) and roll is as above.

The hemisphere pose (θ, φ) at radius r is the free camera at ``r (sinθ cosφ, sinθ sinφ, cosθ)``
with yaw φ + 180°, pitch 90° − θ and roll 0 (:func:`free_camera_of_pose`).

Intrinsics, in pixels of the rendered film (pixel (0, 0) is the top-left corner of the top-left
pixel): either ``fov_deg`` (horizontal, square pixels, principal point at the film's centre: the
scene file's camera), or ``fx_px`` and ``fy_px`` with optional ``cx_px``, ``cy_px`` (the film's
centre when left out), as OpenCV's camera matrix. Neither gives the scene camera's fov. Lens
distortion ``k1, k2, p1, p2, k3`` is OpenCV's (Brown–Conrady) model on normalised coordinates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ConfigDict, Field, ValidationInfo, field_validator, model_validator

from services.common.base import FrozenModel, Number
from services.common.geometry.camera import PinholeCamera, focal_length_px, fov_deg_of
from services.common.geometry.pose import Pose

__all__ = [
    "rotation_angle_deg",
    "FreeCamera",
    "LensDistortion",
    "attitude_error_deg",
    "direction_pose",
    "free_camera_of_pose",
    "free_pinhole_camera",
    "look_at_angles",
    "orbit_position",
    "quaternion_of_rotation",
    "rotation_of_quaternion",
    "rotation_of_yaw_pitch_roll",
    "yaw_pitch_roll_of_rotation",
]

FloatArray = NDArray[np.float64]

Coordinate = Annotated[Number, Field(ge=-1e4, le=1e4)]
Point3 = tuple[Coordinate, Coordinate, Coordinate]
FovDeg = Annotated[Number, Field(gt=0.0, lt=180.0)]
FocalPx = Annotated[Number, Field(gt=0.0, le=1e6)]
PixelCoordinate = Annotated[Number, Field(ge=-1e6, le=1e6)]
Coefficient = Annotated[Number, Field(ge=-1e3, le=1e3)]
MIN_QUATERNION_NORM = 1e-6


class LensDistortion(FrozenModel):
    """OpenCV's radial and tangential lens distortion (``k1, k2, p1, p2, k3``).

    On normalised coordinates (x, y) = (X_c / Z_c, Y_c / Z_c), with r² = x² + y²::

        x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
        y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y

    and the pixel is ``(fx x_d + cx, fy y_d + cy)``, as ``cv2.projectPoints``.
    """

    k1: Coefficient = 0.0
    k2: Coefficient = 0.0
    p1: Coefficient = 0.0
    p2: Coefficient = 0.0
    k3: Coefficient = 0.0

    @classmethod
    def of_coefficients(cls, values: Sequence[float]) -> LensDistortion:
        """A lens from OpenCV's ``distCoeffs`` order: ``k1, k2, p1, p2`` and optionally ``k3``.
        Raises ``ValueError`` for any other count, and pydantic's for values out of range."""
        if len(values) not in (4, 5):
            raise ValueError(f"k1,k2,p1,p2 and optionally k3: 4 or 5 numbers, not {len(values)}")
        return cls.model_validate(dict(zip(("k1", "k2", "p1", "p2", "k3"), values, strict=False)))

    @property
    def is_zero(self) -> bool:
        """Whether this is no distortion at all (a pinhole image)."""
        return self.k1 == self.k2 == self.p1 == self.p2 == self.k3 == 0.0

    def coefficients(self) -> FloatArray:
        """``(k1, k2, p1, p2, k3)`` as OpenCV's ``distCoeffs``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)


def _free_camera_schema(schema: dict[str, Any]) -> None:
    """Publish the orientation forms: exactly one of a quaternion, yaw and pitch, or a look-at."""
    forms = (["quaternion_wxyz"], ["yaw_deg", "pitch_deg"], ["look_at"])
    keys = {key for form in forms for key in form}
    schema["oneOf"] = [
        {"required": form, "not": {"anyOf": [{"required": [k]} for k in sorted(keys - set(form))]}}
        for form in forms
    ]


class FreeCamera(FrozenModel):
    """A camera anywhere in the scene: a position, one orientation form, optional intrinsics.

    See :mod:`services.common.geometry.free_camera` for the conventions.
    """

    model_config = ConfigDict(json_schema_extra=_free_camera_schema)

    position: Point3 = Field(
        description="Camera centre in world units (scene frame: z up, the ground at z = 0)."
    )
    quaternion_wxyz: tuple[Number, Number, Number, Number] | None = Field(
        default=None,
        description="Camera-to-world rotation as a quaternion (w, x, y, z), camera axes x right, "
        "y down, z forward (OpenCV); normalised, so any non-zero length is accepted.",
    )
    yaw_deg: Number | None = Field(
        default=None,
        description="Direction of the optical axis about world +z, counter-clockwise from +x.",
    )
    pitch_deg: Annotated[Number, Field(ge=-90.0, le=90.0)] | None = Field(
        default=None,
        description="Angle of the optical axis below the horizontal: 90 looks straight down.",
    )
    look_at: Point3 | None = Field(
        default=None, description="World point the optical axis goes through."
    )
    roll_deg: Number = Field(
        default=0.0,
        description="Turn about the optical axis (with yaw/pitch or look_at), right-handed about "
        "the forward axis: the world in the image turns counter-clockwise by this angle.",
    )
    fov_deg: FovDeg | None = Field(
        default=None,
        description="Horizontal field of view (square pixels, centred principal point); the "
        "scene camera's when neither it nor fx_px is given.",
    )
    fx_px: FocalPx | None = Field(default=None, description="Focal length along x, in pixels.")
    fy_px: FocalPx | None = Field(default=None, description="Focal length along y, in pixels.")
    cx_px: PixelCoordinate | None = Field(
        default=None, description="Principal point x in pixels (from the left edge of the film)."
    )
    cy_px: PixelCoordinate | None = Field(
        default=None, description="Principal point y in pixels (from the top edge of the film)."
    )
    distortion: LensDistortion | None = Field(
        default=None, description="OpenCV lens distortion of the image; none by default."
    )

    @field_validator("quaternion_wxyz")
    @classmethod
    def _non_zero(
        cls, value: tuple[float, float, float, float] | None
    ) -> tuple[float, float, float, float] | None:
        if value is not None and math.hypot(*value) < MIN_QUATERNION_NORM:
            raise ValueError("a rotation quaternion must not have zero length")
        return value

    @field_validator("look_at")
    @classmethod
    def _away_from_position(
        cls, value: tuple[float, float, float] | None, info: ValidationInfo
    ) -> tuple[float, float, float] | None:
        position = info.data.get("position")
        if value is not None and position is not None and math.dist(value, position) < 1e-9:
            raise ValueError("the look-at point must differ from the camera's position")
        return value

    @model_validator(mode="after")
    def _one_orientation_and_intrinsics(self) -> FreeCamera:
        angles = (self.yaw_deg is not None, self.pitch_deg is not None)
        forms = [self.quaternion_wxyz is not None, any(angles), self.look_at is not None]
        if sum(forms) != 1:
            raise ValueError(
                "give exactly one orientation: quaternion_wxyz, yaw_deg/pitch_deg or look_at"
            )
        if any(angles) and not all(angles):
            raise ValueError("yaw_deg and pitch_deg go together")
        if self.quaternion_wxyz is not None and self.roll_deg != 0.0:
            raise ValueError("roll_deg goes with yaw_deg/pitch_deg or look_at, not a quaternion")
        focal = (self.fx_px is not None, self.fy_px is not None)
        if any(focal) and not all(focal):
            raise ValueError("fx_px and fy_px go together")
        if self.fov_deg is not None and any(focal):
            raise ValueError("give fov_deg or fx_px/fy_px, not both")
        if (self.cx_px is not None or self.cy_px is not None) and not all(focal):
            raise ValueError("cx_px and cy_px go with fx_px and fy_px")
        return self

    def rotation(self) -> FloatArray:
        """The 3x3 camera-to-world rotation R_cw (columns: right, down, forward in world axes)."""
        if self.quaternion_wxyz is not None:
            return rotation_of_quaternion(self.quaternion_wxyz)
        if self.look_at is not None:
            yaw, pitch = look_at_angles(self.position, self.look_at)
            return rotation_of_yaw_pitch_roll(yaw, pitch, self.roll_deg)
        if self.yaw_deg is None or self.pitch_deg is None:  # the validator makes this unreachable
            raise ValueError("no orientation given")
        return rotation_of_yaw_pitch_roll(self.yaw_deg, self.pitch_deg, self.roll_deg)


def rotation_of_quaternion(q: ArrayLike) -> FloatArray:
    """The rotation matrix of quaternion ``q = (w, x, y, z)`` (normalised here)::

    R = [[1 - 2(y² + z²), 2(xy - wz),     2(xz + wy)],
         [2(xy + wz),     1 - 2(x² + z²), 2(yz - wx)],
         [2(xz - wy),     2(yz + wx),     1 - 2(x² + y²)]]
    """
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_angle_deg(a: ArrayLike, b: ArrayLike) -> float:
    """The angle (degrees) of the rotation between rotation matrices ``a`` and ``b``:
    ``θ = acos((tr(AᵀB) − 1) / 2)``, clipped against rounding."""
    cosine = (float(np.trace(np.asarray(a, dtype=np.float64).T @ np.asarray(b))) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def attitude_error_deg(rotation_cw: ArrayLike, pitch_deg: float, roll_deg: float) -> float:
    """How far (degrees) the camera of rotation ``rotation_cw`` (camera-to-world) is from the
    attitude ``pitch_deg``, ``roll_deg`` (module docstring; any yaw): the angle between the
    world's down ``g = (0, 0, -1)`` in either camera's axes, ``acos(R_cwᵀ g · R(0, ϑ, ρ)ᵀ g)``.
    It leaves the heading out, so it is defined at the nadir too, where roll and yaw merge."""
    down = np.array([0.0, 0.0, -1.0])
    seen = np.asarray(rotation_cw, dtype=np.float64).T @ down
    stated = rotation_of_yaw_pitch_roll(0.0, pitch_deg, roll_deg).T @ down
    return math.degrees(math.acos(min(1.0, max(-1.0, float(seen @ stated)))))


def quaternion_of_rotation(rotation: ArrayLike) -> tuple[float, float, float, float]:
    """The unit quaternion ``(w, x, y, z)`` of a rotation matrix, with w ≥ 0 (Shepperd's method:
    the largest of w², x², y², z² is taken from the diagonal, so no division is ill-conditioned)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    squares = [trace, m[0, 0], m[1, 1], m[2, 2]]
    best = int(np.argmax(squares))
    if best == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = best - 1
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 0.0))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    quat = np.asarray(q) / np.linalg.norm(q)
    if quat[0] < 0:
        quat = -quat
    return (float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3]))


def rotation_of_yaw_pitch_roll(yaw_deg: float, pitch_deg: float, roll_deg: float) -> FloatArray:
    """The camera-to-world rotation of yaw ψ, pitch ϑ and roll ρ (module docstring)::

    f = (cos ϑ cos ψ, cos ϑ sin ψ, -sin ϑ),  r₀ = (sin ψ, -cos ψ, 0),  d₀ = f × r₀
    right = r₀ cos ρ + d₀ sin ρ,  down = d₀ cos ρ - r₀ sin ρ
    """
    psi, theta, rho = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    forward = np.array(
        [math.cos(theta) * math.cos(psi), math.cos(theta) * math.sin(psi), -math.sin(theta)]
    )
    right0 = np.array([math.sin(psi), -math.cos(psi), 0.0])
    down0 = np.cross(forward, right0)
    right = right0 * math.cos(rho) + down0 * math.sin(rho)
    down = down0 * math.cos(rho) - right0 * math.sin(rho)
    return np.stack([right, down, forward], axis=1)


def yaw_pitch_roll_of_rotation(rotation: ArrayLike) -> tuple[float, float, float]:
    """Yaw, pitch and roll in degrees of a camera-to-world rotation: the inverse of
    :func:`rotation_of_yaw_pitch_roll` (yaw 0 when the optical axis is vertical)::

        ϑ = asin(-f_z),  ψ = atan2(f_y, f_x),  ρ = atan2(right · d₀, right · r₀)
    """
    m = np.asarray(rotation, dtype=np.float64)
    forward, right = m[:, 2], m[:, 0]
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, -forward[2]))))
    yaw, _ = look_at_angles((0.0, 0.0, 0.0), forward)
    psi = math.radians(yaw)
    right0 = np.array([math.sin(psi), -math.cos(psi), 0.0])
    down0 = np.cross(forward, right0)
    roll = math.degrees(math.atan2(float(right @ down0), float(right @ right0)))
    return yaw, pitch, roll


def look_at_angles(position: ArrayLike, target: ArrayLike) -> tuple[float, float]:
    """Yaw and pitch in degrees of the direction from ``position`` to ``target`` (yaw 0 when it
    is vertical to within rounding)."""
    d = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    horizontal = math.hypot(d[0], d[1])
    # Within rounding of vertical, the yaw is noise: take 0.
    vertical = horizontal <= 1e-12 * abs(d[2])
    yaw = 0.0 if vertical else math.degrees(math.atan2(d[1], d[0]))
    return yaw, math.degrees(math.atan2(-d[2], horizontal))


def free_pinhole_camera(
    camera: FreeCamera, width: int, height: int, default_fov_deg: float
) -> PinholeCamera:
    """The pinhole part of ``camera`` on a ``width`` x ``height`` film: intrinsics and
    world-to-camera extrinsics (``R = R_cwᵀ``, ``t = -R c``); the distortion is not in it."""
    if camera.fx_px is not None and camera.fy_px is not None:
        fx, fy = camera.fx_px, camera.fy_px
        cx = camera.cx_px if camera.cx_px is not None else width / 2.0
        cy = camera.cy_px if camera.cy_px is not None else height / 2.0
    else:
        fov = camera.fov_deg if camera.fov_deg is not None else default_fov_deg
        fx = fy = focal_length_px(fov, width)
        cx, cy = width / 2.0, height / 2.0
    rotation = camera.rotation().T
    position = np.asarray(camera.position, dtype=np.float64)
    translation = -rotation @ position
    return PinholeCamera(
        width=width,
        height=height,
        fov_deg=fov_deg_of(fx, width),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        rotation=tuple(tuple(float(v) for v in row) for row in rotation),
        translation=(float(translation[0]), float(translation[1]), float(translation[2])),
        position=(float(position[0]), float(position[1]), float(position[2])),
    )


def orbit_position(
    look: tuple[float, float, float], distance: float, elevation_deg: float, azimuth_deg: float
) -> tuple[float, float, float]:
    """The point ``distance`` from ``look`` at ``elevation_deg`` above the ground plane and
    ``azimuth_deg`` from +x: ``look + d (cos ε cos α, cos ε sin α, sin ε)``. A camera there
    looks back at ``look`` with yaw ``α + 180°`` and pitch ``ε``."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    offset = (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))
    x, y, z = (float(p + distance * o) for p, o in zip(look, offset, strict=True))
    return x, y, z


def free_camera_of_pose(pose: Pose, radius: float, fov_deg: float | None = None) -> FreeCamera:
    """The hemisphere pose as a free camera (yaw φ + 180°, pitch 90° − θ, roll 0)."""
    theta, phi = math.radians(pose.theta_deg), math.radians(pose.phi_deg)
    position = (
        radius * math.sin(theta) * math.cos(phi),
        radius * math.sin(theta) * math.sin(phi),
        radius * math.cos(theta),
    )
    return FreeCamera(
        position=position,
        yaw_deg=pose.phi_deg + 180.0,
        pitch_deg=90.0 - pose.theta_deg,
        fov_deg=fov_deg,
    )


def direction_pose(position: ArrayLike) -> Pose:
    """The hemisphere pose in the direction of ``position`` from the scene centre (the origin):
    ``θ = acos(z / |p|)`` (at most 90°: a camera below the horizon counts as on it) and
    ``φ = atan2(y, x)``; θ = 0 at the origin itself. A free camera's nearest grid pose is the
    grid's nearest to this one."""
    x, y, z = (float(v) for v in np.asarray(position, dtype=np.float64))
    norm = math.sqrt(x * x + y * y + z * z)
    theta = math.degrees(math.acos(max(-1.0, min(1.0, z / norm)))) if norm > 0.0 else 0.0
    return Pose(theta_deg=min(theta, 90.0), phi_deg=math.degrees(math.atan2(y, x)))
