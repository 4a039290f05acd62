"""Messages of the free-camera pose: the optimizer's ``POST /free-pose`` and what a free search
answers with it.

A free pose is any camera in the scene's world frame (z up, the ground the plane z = 0, scene
units), with the conventions of :mod:`services.common.geometry.free_camera`: the quaternion is
the camera-to-world rotation, camera axes x right, y down, z forward (OpenCV). Intrinsics are in
pixels of the target image.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import ArrayLike
from pydantic import Field, model_validator

from services.common.base import BoxXYXY, FrozenModel, Integer, Number
from services.common.contracts.optimize import (
    MAX_DETECTIONS,
    GridPose,
    ImageDetections,
    ImageSide,
)
from services.common.geometry.camera import fov_deg_of
from services.common.geometry.free_camera import (
    FocalPx,
    FovDeg,
    FreeCamera,
    LensDistortion,
    PixelCoordinate,
    direction_pose,
    quaternion_of_rotation,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import SCENE_ID_PATTERN

__all__ = [
    "CameraAttitude",
    "DenseReport",
    "FreeAmbiguity",
    "FreeAnswer",
    "FreeCorrespondence",
    "FreePose",
    "FreePoseRequest",
    "FreePoseResponse",
    "FreeStatus",
    "EXACT_SOURCES",
    "IntrinsicsSource",
    "KnownSource",
    "IntrinsicsUsed",
    "PhotoIntrinsics",
    "above_chance",
    "nearest_grid_pose",
]

FreeStatus = Literal["found", "ambiguous", "failed"]
IntrinsicsSource = Literal["given", "calibration", "exif", "estimated", "scene"]
KnownSource = Literal["given", "calibration", "exif"]
"""Where a photo's known intrinsics came from: ``given`` by the user, a drone's ``calibration``
in the photo's XMP, or the focal length its ``exif`` states."""
EXACT_SOURCES: frozenset[str] = frozenset({"given", "calibration"})
"""Sources of the photo's exact intrinsics, which a render may confirm; an EXIF focal length is a
nominal lens (whole millimetres) that no render can check."""
FreeAmbiguity = Literal["few", "rivals", "focal", "loose", "attitude"]
Unit = Annotated[Number, Field(ge=0.0, le=1.0)]
NonNeg = Annotated[Number, Field(ge=0.0)]


class PhotoIntrinsics(FrozenModel):
    """The photo's intrinsics, when known: ``fov_deg`` (horizontal, square pixels, centred
    principal point) or OpenCV's ``fx_px``, ``fy_px`` (with ``cx_px``, ``cy_px``: the image's
    centre when left out), and optionally OpenCV's lens ``distortion`` (which needs one of them);
    ``source`` says whether the user gave them, a drone's calibration in the photo's XMP stated
    them, or its EXIF stated the focal length.
    """

    fov_deg: FovDeg | None = None
    fx_px: FocalPx | None = None
    fy_px: FocalPx | None = None
    cx_px: PixelCoordinate | None = None
    cy_px: PixelCoordinate | None = None
    distortion: LensDistortion | None = None
    source: KnownSource = Field(
        default="given",
        description="`given` by the user, read from the drone's `calibration` in the photo's "
        "XMP, or from the photo's `exif` (its focal length).",
    )

    @model_validator(mode="after")
    def _one_focal(self) -> PhotoIntrinsics:
        focal = (self.fx_px is not None, self.fy_px is not None)
        if any(focal) and not all(focal):
            raise ValueError("fx_px and fy_px go together")
        if self.fov_deg is not None and any(focal):
            raise ValueError("give fov_deg or fx_px/fy_px, not both")
        if (self.cx_px is None) != (self.cy_px is None):
            raise ValueError("cx_px and cy_px go together")
        if self.cx_px is not None and not all(focal):
            raise ValueError("cx_px and cy_px go with fx_px and fy_px")
        if self.fov_deg is None and not any(focal):
            raise ValueError("give fov_deg or fx_px/fy_px (distortion needs the focal length)")
        return self

    def camera_fields(self) -> dict[str, object]:
        """These intrinsics as the fields of a :class:`FreeCamera`."""
        return self.model_dump(exclude_none=True, exclude={"source"})


class CameraAttitude(FrozenModel):
    """The camera's pitch and roll as the photo states them (a drone's gimbal, in its XMP), in
    the conventions of :mod:`services.common.geometry.free_camera`: pitch below the horizontal
    (90°: nadir), roll about the optical axis. No yaw: a drone's is a compass heading, and a
    scene's axes need not point north."""

    pitch_deg: Annotated[Number, Field(ge=-90.0, le=90.0)]
    roll_deg: Annotated[Number, Field(ge=-180.0, le=180.0)]


class FreePoseRequest(FrozenModel):
    """``POST /free-pose``: the scene, the target image's size and detections (boxes in its
    pixels; none is a ``failed`` answer, not an error), the photo's intrinsics if known
    (otherwise the scene camera's field of view is the start and the focal length is estimated
    from four paired objects on), and the network input of the detector that found the boxes
    (``detector_input``: its box errors grow in the image's pixels with the image it shrank;
    without it they are taken as at the image's own size), and the camera's ``attitude`` when
    the photo states it (poses far from it are not answered)."""

    scene: Annotated[str, Field(pattern=SCENE_ID_PATTERN)]
    target: ImageDetections
    intrinsics: PhotoIntrinsics | None = None
    attitude: CameraAttitude | None = Field(
        default=None,
        description="The camera's pitch and roll the photo states (its drone's gimbal): poses "
        "whose down direction lies more than 10° from theirs are not answered.",
    )
    detector_input: tuple[ImageSide, ImageSide] | None = Field(
        default=None,
        description="The detector's network input (width, height) in pixels: the "
        "`model.input_size` of its `/detect` answer.",
    )


class IntrinsicsUsed(FrozenModel):
    """The intrinsics a pose was computed with, in pixels of the target image: ``given`` by the
    request, the drone's ``calibration`` in the photo's XMP, read from the photo's ``exif``,
    ``estimated`` from the boxes, or the ``scene``
    camera's field of view (not given, too few objects to estimate it). ``distortion`` is the
    given lens, if any."""

    fx_px: Number
    fy_px: Number
    cx_px: Number
    cy_px: Number
    fov_deg: Number
    source: IntrinsicsSource
    distortion: LensDistortion | None = None

    def refocused(
        self,
        fx_px: float,
        fy_px: float,
        width: int,
        source: IntrinsicsSource,
        distortion: LensDistortion | None,
    ) -> IntrinsicsUsed:
        """These intrinsics with the focal lengths ``fx_px, fy_px`` (the principal point
        kept), their fov ``2 atan(W / 2 f_x)`` over ``width`` pixels, ``source`` and
        ``distortion``."""
        return IntrinsicsUsed(
            fx_px=fx_px,
            fy_px=fy_px,
            cx_px=self.cx_px,
            cy_px=self.cy_px,
            fov_deg=fov_deg_of(fx_px, width),
            source=source,
            distortion=distortion,
        )


class FreeCorrespondence(FrozenModel):
    """Target detection ``detection`` (its index in the request) is scene object ``object``;
    ``residual_px`` is the pair's box-edge RMS, ``predicted_box`` the object's box projected at
    the pose (target pixels, unclipped)."""

    detection: Annotated[Integer, Field(ge=0, lt=MAX_DETECTIONS)]
    object: str
    label: str
    residual_px: NonNeg
    predicted_box: BoxXYXY | None = None


class FreePose(FrozenModel):
    """A camera pose from the target's boxes: position (scene units), camera-to-world quaternion
    ``(w, x, y, z)`` and yaw/pitch/roll in degrees, the intrinsics used, the pairs, the edge RMS
    residual in pixels, a confidence in [0, 1] and the 1-σ position (scene units) and rotation
    (degrees) uncertainty under the detector's edge noise (null when the boxes do not pin it)."""

    position: tuple[Number, Number, Number]
    quaternion_wxyz: tuple[Number, Number, Number, Number]
    yaw_pitch_roll_deg: tuple[Number, Number, Number]
    intrinsics: IntrinsicsUsed
    correspondences: tuple[FreeCorrespondence, ...]
    residual_px: NonNeg
    confidence: Unit
    position_sigma: NonNeg | None
    rotation_sigma_deg: NonNeg | None

    def camera(self) -> FreeCamera:
        """This pose as the renderer takes it (target pixels)."""
        k = self.intrinsics
        return FreeCamera(
            position=self.position,
            quaternion_wxyz=self.quaternion_wxyz,
            fx_px=k.fx_px,
            fy_px=k.fy_px,
            cx_px=k.cx_px,
            cy_px=k.cy_px,
            distortion=k.distortion,
        )

    def moved_to(
        self,
        camera_to_world: ArrayLike,
        position: ArrayLike,
        intrinsics: IntrinsicsUsed,
        residual_px: float,
    ) -> FreePose:
        """This pose's pairs seen from another camera: its ``camera_to_world`` rotation (3x3),
        ``position``, ``intrinsics`` (target pixels) and edge RMS ``residual_px``."""
        x, y, z = (float(v) for v in np.asarray(position, dtype=np.float64))
        return self.model_copy(
            update={
                "position": (x, y, z),
                "quaternion_wxyz": quaternion_of_rotation(camera_to_world),
                "yaw_pitch_roll_deg": yaw_pitch_roll_of_rotation(camera_to_world),
                "intrinsics": intrinsics,
                "residual_px": residual_px,
            }
        )


class FreePoseResponse(FrozenModel):
    """``POST /free-pose``: ``found`` (a pose the boxes pin, unique), ``ambiguous`` (the best and
    its ``alternatives``: too few objects, a symmetric layout, look-alikes, a loose fit) or
    ``failed`` (no usable detection: ``pose`` null), and why. ``nearest_grid`` is the scene's
    hemisphere grid pose nearest the camera's direction from the scene centre, for comparison
    with a hemisphere search."""

    status: FreeStatus
    reason: str
    pose: FreePose | None
    alternatives: tuple[FreePose, ...] = ()
    nearest_grid: GridPose | None = None
    usable_detections: Annotated[Integer, Field(ge=0)] = 0
    ambiguity: FreeAmbiguity | None = Field(
        default=None,
        description="Why an `ambiguous` answer is: `few` objects paired (under 3); `rivals`, "
        "distinct poses that explain the boxes almost as well; `focal`, 3 objects without "
        "intrinsics; `loose`, one pose that the boxes pin only loosely (a render's edges can "
        "pin it). Null unless ambiguous.",
    )

    @property
    def candidates(self) -> list[FreePose]:
        """The poses to render, best first: the pose, then its alternatives."""
        return [p for p in (self.pose, *self.alternatives) if p is not None]


def above_chance(count: float, total: int, chance: float) -> float:
    """The share of ``total`` edge points that ``count`` of them on the target's edges is above
    ``chance``, the share a pose placed at random would leave there:
    ``(count / total − chance) / (1 − chance)``. If a share ``q`` of the points lie on the edges
    they belong to and the others fall there by chance, ``count / total = q + (1 − q) chance``,
    so this is ``q``. On a plain target it is about the raw share (chance 1–3 % on the free
    bench's renders); on an edge-rich one (gravel, foliage, noise) a wrong pose's raw share
    rises towards the chance, this one does not. 0 when there are no points."""
    if total <= 0:
        return 0.0
    return (count / total - chance) / (1.0 - chance)


class LensBend(FrozenModel):
    """The lens check of a dense fit made without the photo's lens distortion: the radial
    term ``k1`` (OpenCV's, ``x_d = x (1 + k1 r²)``) that the target's edges fit with the pose
    (and the focal length, unless it was given), its standard deviation ``k1_sigma`` (the edge
    points taken as independent), ``bend_px``, how far it moves the farthest explained edge
    points (the 95th percentile, target pixels), how many edge points that fit explains
    (``inliers``) and how much of the pinhole fit's misfit (``cost_drop``); ``bends`` when the
    optimizer judges the bend beyond what a pinhole's fit leaves: the photo was taken through a
    distorting lens, and a pose fitted as a pinhole's is not to be confirmed."""

    k1: Number
    k1_sigma: NonNeg
    bend_px: NonNeg
    inliers: Annotated[Integer, Field(ge=0)]
    bends: bool
    cost_drop: Annotated[Number, Field(le=1.0)] | None = Field(
        default=None,
        description="The share of the pinhole fit's robust edge cost that the k1 fit removes "
        "(1 − cost with k1 / cost without; null for a fit already made through an estimated "
        "lens). A lens that bends yet explains little of the misfit (a moved light's shadow "
        "edges) does not move the answer: the pinhole's pose is kept, still unconfirmed.",
    )


class DenseReport(FrozenModel):
    """How the dense edge refinement of a pose by its render went (``POST /refine-pose``):
    ``converged`` when the render's edges, moved with the pose, fell on the target's edges
    (enough model edge points, at least as many explained as at the start); ``accepted`` when
    the refined pose is also within a plausible move of the start (else the start's is kept);
    ``reason`` says which. ``edge_points`` model edge points were fitted, ``inliers`` of them
    end within 2 px of a target edge (``start_inliers`` at the start), their RMS distance
    ``residual_px`` (target pixels; null when none); ``focal_fitted`` when the focal length was
    fitted too; ``moved`` and ``moved_rotation_deg`` how far the pose moved (scene units,
    degrees); ``render_again`` when the fit moved far from the render (its silhouettes, seen
    from there, bias the fit: its focal length, when fitted, and its pose): a render at the
    refined pose and a refit from it would be closer."""

    converged: bool
    accepted: bool
    reason: str
    edge_points: Annotated[Integer, Field(ge=0)]
    inliers: Annotated[Integer, Field(ge=0)]
    start_inliers: Annotated[Integer, Field(ge=0)]
    residual_px: NonNeg | None
    focal_fitted: bool
    moved: NonNeg
    moved_rotation_deg: NonNeg
    render_again: bool = False
    box_shift_px: NonNeg = Field(
        default=0.0,
        description="RMS shift of the paired objects' predicted box edges from the start "
        "pose's to the fit's (target pixels): a fit that leaves the boxes needs the image's "
        "firm support to be accepted.",
    )
    focal_sigma: NonNeg | None = Field(
        default=None,
        description="Relative standard deviation of the focal length the edges fitted (0.01: "
        "±1 %), from the fit's own curvature with the edge points taken as independent, which "
        "they are not: measured on free targets, the fov's errors reached 3 to 30 times it. "
        "Null when the focal length was not asked for or too few points were explained.",
    )
    chance: Annotated[Number, Field(ge=0.0, lt=1.0)] = Field(
        default=0.0,
        description="The share of the edge points that a pose placed at random would leave "
        "within 2 px of a target edge of their orientation: the target's edge density. The "
        "shares that decide are taken above it (``above_chance``); 0 from an optimizer that "
        "does not say.",
    )
    lead: bool = Field(
        default=False,
        description="The fit moved too far to be accepted, yet the image vouches for where it "
        "ended (most of its edge points on the target's, several times the start's): not an "
        "answer, but a pose worth rendering to check. False from an optimizer that does not say.",
    )
    lens: LensBend | None = Field(
        default=None,
        description="The lens check, made when no lens distortion was known: whether the "
        "target's edges bend as a distorting lens would. Null when not made.",
    )

    def share(self, count: int | None = None) -> float:
        """The share of the edge points that ``count`` (the fit's ``inliers`` by default) is
        above :attr:`chance` (:func:`above_chance`)."""
        return above_chance(self.inliers if count is None else count, self.edge_points, self.chance)


class FreeAnswer(FrozenModel):
    """What a free search found (``SearchResult.free``): the pose from the target's boxes
    confirmed (or not) by rendering it. ``status`` is ``found`` only when the pose was unique
    and its render's detections agreed with the target's box by box; ``renders`` counts the
    views rendered to check it; ``alternatives`` are the other poses that explain the target."""

    status: FreeStatus
    pose: FreePose
    alternatives: tuple[FreePose, ...] = ()
    nearest_grid: GridPose
    renders: Annotated[Integer, Field(ge=0)]
    match_rms_px: NonNeg | None = Field(
        default=None,
        description="Box-edge RMS between the target's detections and those of the render at "
        "the pose (target pixels); null when no pair was found.",
    )
    box_pose: FreePose | None = Field(
        default=None,
        description="The pose from the target's boxes, when ``pose`` is that pose refined "
        "densely against the target image by its render.",
    )
    dense: DenseReport | None = Field(
        default=None,
        description="How the dense refinement by the confirming render went; null when none "
        "was made (no render agreed with the target).",
    )


def nearest_grid_pose(position: tuple[float, float, float], grid: HemisphereGrid) -> GridPose:
    """The grid pose nearest the direction of ``position`` from the scene centre
    (:func:`~services.common.geometry.free_camera.direction_pose`)."""
    index = grid.nearest(direction_pose(position))
    pose = grid.pose(index)
    return GridPose(index=index, theta_deg=pose.theta_deg, phi_deg=pose.phi_deg)
