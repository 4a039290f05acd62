"""What the pose from boxes alone answers: a status, the best pose, its rivals, their evidence.

Frozen dataclasses of the domain; the HTTP contract that carries them comes with the route.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from services.common.geometry.free_camera import FreeCamera
from services.optimizer.geometry import FloatArray

__all__ = [
    "Ambiguity",
    "Correspondence",
    "FreePoseAnswer",
    "IntrinsicsSource",
    "IntrinsicsUsed",
    "KnownSource",
    "PoseCandidate",
    "Status",
]

Status = Literal["found", "ambiguous", "failed"]
Ambiguity = Literal["few", "rivals", "focal", "loose", "attitude"]
"""Why an answer is ``ambiguous``: ``few`` objects paired (under 3); ``rivals``, distinct poses
that explain the boxes almost as well; ``focal``, 3 objects and no intrinsics (the scene
camera's fov assumed); ``loose``, one pose whose boxes pin it only loosely (its σ);
``attitude``, no pose that explains the boxes has the camera's attitude the photo states."""
IntrinsicsSource = Literal["given", "calibration", "exif", "estimated", "scene"]
KnownSource = Literal["given", "calibration", "exif"]
"""Where known intrinsics came from: the user, a drone's calibration, or an EXIF focal length."""


@dataclass(frozen=True)
class Correspondence:
    """Detection ``detection`` (its index in the request) is object ``object``."""

    detection: int
    object: str
    label: str
    residual_px: float


@dataclass(frozen=True)
class IntrinsicsUsed:
    """The intrinsics a pose was computed with: ``given``, read from the photo's ``exif`` (as
    good as given), ``estimated`` from the boxes, or the ``scene`` camera's field of view (not
    given, too few pairs to estimate)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    fov_deg: float
    source: IntrinsicsSource


@dataclass(frozen=True)
class PoseCandidate:
    """A camera pose: position (world, scene units), camera-to-world quaternion ``(w, x, y, z)``
    and yaw/pitch/roll (the conventions of :mod:`services.common.geometry.free_camera`), the
    intrinsics, the edge RMS residual in pixels, the pairs it explains, and its 1-σ position and
    rotation uncertainty under :data:`~.tolerances.NOISE_FLOOR_PX` of edge noise (:func:`~.refine.
    pose_uncertainty`: how firmly the boxes pin this pose; inf when they do not)."""

    position: tuple[float, float, float]
    quaternion_wxyz: tuple[float, float, float, float]
    yaw_pitch_roll_deg: tuple[float, float, float]
    intrinsics: IntrinsicsUsed
    residual_px: float
    correspondences: tuple[Correspondence, ...]
    position_sigma: float
    rotation_sigma_deg: float

    @property
    def inliers(self) -> int:
        return len(self.correspondences)

    def free_camera(self) -> FreeCamera:
        """This pose as the renderer takes it."""
        k = self.intrinsics
        return FreeCamera(
            position=self.position,
            quaternion_wxyz=self.quaternion_wxyz,
            fx_px=k.fx_px,
            fy_px=k.fy_px,
            cx_px=k.cx_px,
            cy_px=k.cy_px,
        )

    def rotation(self) -> FloatArray:
        """The camera-to-world rotation."""
        return FreeCamera(position=self.position, quaternion_wxyz=self.quaternion_wxyz).rotation()

    def in_target_pixels(self, scale: float) -> PoseCandidate:
        """This pose solved on the image shrunk ``scale`` times, in the image's own pixels: the
        pixel intrinsics and the residuals times ``scale`` (the fov and pose are the same)."""
        if scale == 1.0:
            return self
        k = self.intrinsics
        pixels = replace(
            k,
            fx_px=k.fx_px * scale,
            fy_px=k.fy_px * scale,
            cx_px=k.cx_px * scale,
            cy_px=k.cy_px * scale,
        )
        pairs = tuple(replace(c, residual_px=c.residual_px * scale) for c in self.correspondences)
        return replace(
            self, intrinsics=pixels, residual_px=self.residual_px * scale, correspondences=pairs
        )


@dataclass(frozen=True)
class FreePoseAnswer:
    """The pose from the boxes alone (:mod:`.solve`): ``pose`` is None only when ``failed``;
    ``ambiguity`` says why an ``ambiguous`` one is."""

    status: Status
    reason: str
    pose: PoseCandidate | None
    alternatives: tuple[PoseCandidate, ...]
    usable_detections: int
    ambiguity: Ambiguity | None = None

    def in_target_pixels(self, scale: float) -> FreePoseAnswer:
        """This answer's poses in the image's pixels (:meth:`PoseCandidate.in_target_pixels`)."""
        return replace(
            self,
            pose=None if self.pose is None else self.pose.in_target_pixels(scale),
            alternatives=tuple(a.in_target_pixels(scale) for a in self.alternatives),
        )
