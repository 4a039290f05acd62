"""Pydantic message models shared by every service: poses, grid indices, renders, annotations.

Every model is frozen and strict about unknown keys, so a typo in a request is an error, not a
silently ignored field. The scene-file models live in :mod:`services.common.scene`.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = [
    "Angle",
    "BoxXYXY",
    "CameraModel",
    "DetectResponse",
    "DetectorHealth",
    "DetectorModels",
    "Detection",
    "FrozenModel",
    "GridIndex",
    "GridInfo",
    "GridRing",
    "ModelInfo",
    "ObjectAnnotation",
    "Pose",
    "PoseQuery",
    "RenderAnnotations",
    "RenderHealth",
    "RenderRequest",
    "SceneModelState",
    "SceneModelStatus",
    "SceneSummary",
]


class FrozenModel(BaseModel):
    """Base of all shared messages: immutable, unknown keys rejected, NaN/inf rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Angle = Annotated[float, Field(allow_inf_nan=False)]
ThetaDeg = Annotated[float, Field(ge=0.0, le=90.0, allow_inf_nan=False)]
NonNegInt = Annotated[int, Field(ge=0)]


class Pose(FrozenModel):
    """A camera pose on the hemisphere (paper eq. 1).

    ``theta_deg`` is the polar angle from the zenith (+z), ``phi_deg`` the azimuth from +x
    counter-clockwise seen from above, normalised to [0, 360). The camera sits at
    ``radius * (sin θ cos φ, sin θ sin φ, cos θ)`` and looks at the origin.
    """

    theta_deg: ThetaDeg
    phi_deg: Angle

    @field_validator("phi_deg")
    @classmethod
    def _wrap_phi(cls, value: float) -> float:
        wrapped = math.fmod(value, 360.0)
        if wrapped < 0.0:
            wrapped += 360.0
        # fmod of a tiny negative number can land exactly on 360.0 after the addition.
        return 0.0 if wrapped >= 360.0 else wrapped


class GridIndex(FrozenModel):
    """A grid pose by indices: ``lat`` counts rings from the lowest θ in range, ``lon`` counts
    positions on that ring from φ = 0 counter-clockwise."""

    lat: NonNegInt
    lon: NonNegInt


def _pose_query_schema(schema: dict[str, Any]) -> None:
    """Publish exactly what :class:`PoseQuery` accepts: the keys of one form, never null."""
    for prop in schema["properties"].values():
        variants = [v for v in prop.pop("anyOf", []) if v.get("type") != "null"]
        if variants:
            prop.update(variants[0])
        prop.pop("default", None)

    def form(keys: tuple[str, str], others: tuple[str, str]) -> dict[str, Any]:
        return {"required": list(keys), "not": {"anyOf": [{"required": [k]} for k in others]}}

    angles, indices = ("theta_deg", "phi_deg"), ("lat", "lon")
    schema["oneOf"] = [form(angles, indices), form(indices, angles)]


class PoseQuery(FrozenModel):
    """A pose in a request: either angles (``theta_deg`` and ``phi_deg``) or grid indices
    (``lat`` and ``lon``), not both."""

    model_config = ConfigDict(json_schema_extra=_pose_query_schema)

    theta_deg: ThetaDeg | None = None
    phi_deg: Angle | None = None
    lat: NonNegInt | None = None
    lon: NonNegInt | None = None

    @field_validator("theta_deg", "phi_deg", "lat", "lon", mode="before")
    @classmethod
    def _not_null(cls, value: object) -> object:
        if value is None:
            raise ValueError("must be a number, not null")
        return value

    @model_validator(mode="after")
    def _one_form(self) -> PoseQuery:
        angles = (self.theta_deg is not None, self.phi_deg is not None)
        indices = (self.lat is not None, self.lon is not None)
        if any(angles) and any(indices):
            raise ValueError("give either theta_deg/phi_deg or lat/lon, not both")
        if any(angles) and not all(angles):
            raise ValueError("theta_deg and phi_deg go together")
        if any(indices) and not all(indices):
            raise ValueError("lat and lon go together")
        if not any(angles) and not any(indices):
            raise ValueError("give theta_deg/phi_deg or lat/lon")
        return self

    def as_pose(self) -> Pose | None:
        """The angles as a :class:`Pose`, or None for a grid query."""
        if self.theta_deg is None or self.phi_deg is None:
            return None
        return Pose(theta_deg=self.theta_deg, phi_deg=self.phi_deg)

    def as_index(self) -> GridIndex | None:
        """The grid indices, or None for an angle query."""
        if self.lat is None or self.lon is None:
            return None
        return GridIndex(lat=self.lat, lon=self.lon)


class GridRing(FrozenModel):
    """One ring of the hemisphere grid."""

    lat: NonNegInt
    theta_deg: ThetaDeg
    count: Annotated[int, Field(ge=1)]


class GridInfo(FrozenModel):
    """The discretised hemisphere of a scene: its rings and total number of poses."""

    angle_step_deg: Annotated[float, Field(gt=0.0, le=90.0)]
    min_theta_deg: ThetaDeg
    max_theta_deg: ThetaDeg
    rings: Annotated[tuple[GridRing, ...], Field(min_length=1)]
    size: Annotated[int, Field(ge=1)]


BoxXYXY = tuple[float, float, float, float]


class RenderRequest(FrozenModel):
    """``POST /render``: a scene, a pose (continuous or grid indices) and optional film settings."""

    scene: Annotated[str, Field(min_length=1, max_length=128)]
    pose: PoseQuery
    width: Annotated[int, Field(ge=8)] | None = None
    height: Annotated[int, Field(ge=8)] | None = None
    spp: Annotated[int, Field(ge=1)] | None = None
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0


class CameraModel(FrozenModel):
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


class ObjectAnnotation(FrozenModel):
    """Ground truth for one scene object in one rendered view."""

    name: str
    shape: str = Field(description="The object's class: sphere, cube, cylinder, cone or mesh.")
    position: tuple[float, float, float] = Field(
        description="World position of the object's footprint centre on the ground (z = 0)."
    )
    centroid: tuple[float, float, float] = Field(
        description="World position of the object's bounding-box centre."
    )
    box: BoxXYXY | None = Field(
        description="Pixel box [x1, y1, x2, y2] of the visible silhouette (pixel edges), "
        "or null when no pixel of the object is visible."
    )
    visible_pixels: NonNegInt
    full_box: BoxXYXY | None = Field(
        description="Pixel box of the unoccluded silhouette, clipped to the image."
    )
    full_pixels: NonNegInt = Field(
        description="Pixels the object would cover inside the image with nothing in front of it."
    )
    visible_fraction: Annotated[float, Field(ge=0.0, le=1.0)]
    projected_center: tuple[float, float] = Field(
        description="Pinhole projection of ``centroid`` in pixels (may lie outside the image)."
    )


class RenderAnnotations(FrozenModel):
    """``POST /render/annotations``: per-object ground truth and the camera of the view."""

    scene: str
    pose: Pose
    grid_index: GridIndex | None
    camera: CameraModel
    objects: tuple[ObjectAnnotation, ...]


class SceneSummary(FrozenModel):
    """One entry of ``GET /scenes``."""

    id: str
    objects: int
    grid_size: int
    width: int
    height: int


class RenderHealth(FrozenModel):
    """``GET /health`` of the renderer."""

    status: Literal["ok"]
    service: Literal["renderer"]
    variant: str
    scenes_loaded: tuple[str, ...]
    scenes_available: int
    in_flight: NonNegInt


Rgb255 = tuple[
    Annotated[float, Field(ge=0.0, le=255.0)],
    Annotated[float, Field(ge=0.0, le=255.0)],
    Annotated[float, Field(ge=0.0, le=255.0)],
]


class Detection(FrozenModel):
    """One object found in an image.

    ``box`` is ``[x1, y1, x2, y2]`` in pixels of the image that was sent (pixel edges: the box of
    a single pixel at column 3, row 5 is ``[3, 5, 4, 6]``). ``color`` is the mean sRGB colour
    (0–255) of the object's own pixels inside the box, ground excluded, or null when it could not
    be measured.
    """

    label: Annotated[str, Field(min_length=1, max_length=64)]
    class_id: NonNegInt
    confidence: Annotated[float, Field(ge=0.0, le=1.0)]
    box: BoxXYXY
    color: Rgb255 | None = None


class ModelInfo(FrozenModel):
    """The detector model a service runs."""

    name: str
    classes: tuple[str, ...]
    input_size: tuple[int, int] = Field(description="Network input (width, height) in pixels.")
    sha256: str
    provenance: dict[str, str | int | float] = Field(default_factory=dict)
    scene: str | None = Field(
        default=None,
        description="The scene this model was onboarded for (its classes are that scene's "
        "objects); null for the general model, whose classes are shape types.",
    )


class DetectResponse(FrozenModel):
    """``POST /detect``: the detections and the size (width, height) of the image they refer to."""

    detections: tuple[Detection, ...]
    image_size: tuple[int, int]
    model: ModelInfo
    inference_ms: Annotated[float, Field(ge=0.0)] = 0.0


class DetectorHealth(FrozenModel):
    """``GET /health`` of the detector."""

    status: Literal["ok"]
    service: Literal["detector"]
    model: str
    model_sha256: str
    in_flight: NonNegInt
    providers: tuple[str, ...] = Field(description="onnxruntime execution providers in use.")
    intra_op_threads: NonNegInt = Field(
        description="onnxruntime intra-op threads (0: one per core)."
    )
    max_batch: Annotated[int, Field(ge=1)] = Field(description="Images per inference run.")
    batches_run: NonNegInt
    images_run: NonNegInt
    scene_models: NonNegInt = Field(
        default=0, description="Scenes whose own model is serving (see GET /models)."
    )


SceneModelState = Literal["serving", "refused", "none"]


class SceneModelStatus(FrozenModel):
    """One scene's own detector as the detector service sees it."""

    scene: str
    state: SceneModelState = Field(
        description="The scene's newest model file: `serving` (validated and in use), `refused` "
        "(unloadable, or its sha256, scene or classes do not match: see `error`), `none` (the "
        "scene has no model)."
    )
    model: ModelInfo | None = Field(
        default=None,
        description="The scene model answering this scene's requests: the newest when serving, "
        "the previous one when the newest was refused; null when the general model serves it.",
    )
    error: str | None = Field(default=None, description="Why the newest model was refused.")
    classes: NonNegInt = Field(
        description="Classes a model of this scene must have: one per object, look-alikes shared."
    )


class DetectorModels(FrozenModel):
    """``GET /models``: the general model and every scene's own model."""

    general: ModelInfo
    scenes: tuple[SceneModelStatus, ...]
