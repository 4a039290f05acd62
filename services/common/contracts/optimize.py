"""Messages of the optimizer service: next-pose requests and answers, object mapping.

The optimizer knows no scenes: a request carries the grid and the camera (or names a scene whose
camera and grid the service looks up), the target image's detections and the visited poses with
theirs. Every model is frozen and rejects unknown keys (:class:`~services.common.base.FrozenModel`).
"""

from __future__ import annotations

from typing import Annotated, Any, Final, Literal

from pydantic import AfterValidator, BeforeValidator, ConfigDict, Field, field_validator

from services.common.base import FrozenModel, Integer, Number
from services.common.contracts.detect import Detection
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.geometry.scene import SCENE_ID_PATTERN, CameraSpec
from services.common.scene_models import ObjectClass

__all__ = [
    "CandidatePose",
    "GridPose",
    "ImageDetections",
    "MAX_DETECTIONS",
    "MAX_HISTORY",
    "MIN_SEARCH_STEP_DEG",
    "MapRequest",
    "MapResponse",
    "MappedObject",
    "MappingMethod",
    "Move",
    "NextPoseRequest",
    "NextPoseResponse",
    "OptimizerHealth",
    "PoseEstimate",
    "SearchTolerances",
    "SearchableGrid",
    "StrategyInfo",
    "StrategyName",
    "TargetImage",
    "UnsupportedGridError",
    "ViewMatch",
    "VisitedView",
    "optional_not_null",
    "searchable_grid",
]

MAX_DETECTIONS = 64
"""Detections per image a request may carry."""

MAX_HISTORY = 200
"""Visited views a request may carry."""

StrategyName = Literal["simple", "paper", "reprojection"]
MappingMethod = Literal["exact", "paper"]
Move = Literal["start", "stay", "N", "S", "E", "W", "jump"]

ImageSide = Annotated[Integer, Field(ge=1, le=16384)]


def _distinct_labels(value: tuple[ObjectClass, ...]) -> tuple[ObjectClass, ...]:
    if len({c.label for c in value}) != len(value):
        raise ValueError("object class labels must be distinct")
    return value


ObjectClasses = Annotated[
    tuple[ObjectClass, ...], Field(min_length=1, max_length=256), AfterValidator(_distinct_labels)
]
"""A scene's own detector classes, as a request gives them: distinct labels."""


class UnsupportedGridError(ValueError):
    """A scene's grid that the scene format allows but the optimizer cannot search.

    ``field`` names the offending setting of the scene's ``search`` section.
    """

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


MIN_SEARCH_STEP_DEG: Final = 1.0
"""The finest grid step the optimizer searches: a full hemisphere at 1° holds about 21 000
poses, which bounds the work of scoring every pose. The scene format allows finer grids."""


class SearchableGrid(GridSpec):
    """A :class:`GridSpec` the optimizer can search: its step is at least
    :data:`MIN_SEARCH_STEP_DEG` (the same type, one bound tighter, so errors name the field)."""

    angle_step_deg: Annotated[Number, Field(ge=MIN_SEARCH_STEP_DEG, le=90.0)] = 7.5


def _grid_fields(value: object) -> object:
    """Read a :class:`GridSpec` by its fields, so the tighter bound applies and names its field."""
    return value.model_dump() if isinstance(value, GridSpec) else value


SearchGrid = Annotated[SearchableGrid, BeforeValidator(_grid_fields)]
"""A request's grid: a :class:`GridSpec` (or its JSON) read as a :class:`SearchableGrid`."""


def searchable_grid(grid: GridSpec) -> SearchableGrid:
    """``grid`` as a :class:`SearchableGrid`, when the optimizer can search it.

    Raises :class:`UnsupportedGridError` for a step under :data:`MIN_SEARCH_STEP_DEG`: a scene
    file with such a grid is valid, so this is the caller's 422, not a bug.
    """
    if grid.angle_step_deg < MIN_SEARCH_STEP_DEG:
        raise UnsupportedGridError(
            f"search.angle_step_deg: the optimizer searches grids of at least "
            f"{MIN_SEARCH_STEP_DEG:g}°, got {grid.angle_step_deg:g}°",
            "search.angle_step_deg",
        )
    return SearchableGrid.model_validate(grid.model_dump())


class ImageDetections(FrozenModel):
    """The detections of one image and the image's size (width, height) in pixels.

    Boxes are in that image's pixels; the optimizer scales them to the camera's film. Boxes must
    lie inside the image (checked against ``image_size``; errors name the box).
    """

    image_size: tuple[ImageSide, ImageSide]
    detections: Annotated[tuple[Detection, ...], Field(max_length=MAX_DETECTIONS)] = ()


class TargetImage(ImageDetections):
    """The target image's detections: at least one, or there is nothing to search for."""

    detections: Annotated[tuple[Detection, ...], Field(min_length=1, max_length=MAX_DETECTIONS)]


class VisitedView(ImageDetections):
    """A visited grid pose (``lat``/``lon`` or its exact angles) and what was detected there."""

    pose: PoseQuery


class SearchTolerances(FrozenModel):
    """When two views count as the same (see the strategies' done test).

    ``match_rms_px`` is in the camera's pixels: RMS of box-edge differences between the current
    view and the target under which they match strictly (3× that, grown by the boxes' expected
    edge noise, when the estimate agrees). ``max_unmatched`` bounds the summed confidence of
    each image's unpaired detections.
    """

    match_rms_px: Annotated[Number, Field(gt=0.0, le=1000.0)] = 1.0
    max_unmatched: Annotated[Integer, Field(ge=0, le=MAX_DETECTIONS)] = 1
    ambiguity_ratio: Annotated[Number, Field(ge=1.0, le=100.0)] = 1.25


def optional_not_null(schema: dict[str, Any]) -> None:
    """Publish optional fields as what they accept: the value or nothing, never null."""
    for prop in schema.get("properties", {}).values():
        variants = prop.get("anyOf")
        if variants and any(v.get("type") == "null" for v in variants):
            kept = [v for v in variants if v.get("type") != "null"]
            del prop["anyOf"]
            if len(kept) == 1:
                prop.update(kept[0])
            else:
                prop["anyOf"] = kept
            if prop.get("default", 0) is None:
                del prop["default"]


def _next_pose_schema(schema: dict[str, Any]) -> None:
    """Optional fields as in :func:`optional_not_null`, and the one rule among them a schema
    can say: a ``scene``, or both ``camera`` and ``grid``."""
    optional_not_null(schema)
    schema["anyOf"] = [{"required": ["scene"]}, {"required": ["camera", "grid"]}]


class NextPoseRequest(FrozenModel):
    """``POST /next-pose``: one stateless planning step.

    Give ``camera`` and ``grid``, or a ``scene`` id whose camera and grid the service looks up
    (explicit ``camera``/``grid`` must then agree with the scene's). ``history`` lists the
    visited poses in order; the last one is where the camera is now. ``strategy`` defaults to
    the service's setting (``reprojection`` unless configured).

    ``object_classes``, when given, says the detections came from the scene's own detector:
    every label is one of these classes (an object, or look-alike objects sharing a class),
    detections pair only with equal labels and each class's ``shape`` gives its proxy. Left
    out, labels are the general detector's shape classes, which may be wrong: different
    classes may still pair, at a cost.
    """

    model_config = ConfigDict(json_schema_extra=_next_pose_schema)

    strategy: StrategyName | None = None
    scene: Annotated[str, Field(pattern=SCENE_ID_PATTERN)] | None = None
    camera: CameraSpec | None = None
    grid: SearchGrid | None = None
    target: TargetImage
    history: Annotated[tuple[VisitedView, ...], Field(max_length=MAX_HISTORY)] = ()
    tolerances: SearchTolerances = SearchTolerances()
    object_classes: ObjectClasses | None = None

    @field_validator("strategy", "scene", "camera", "grid", "object_classes", mode="before")
    @classmethod
    def _not_null(cls, value: object) -> object:
        if value is None:
            raise ValueError("leave the field out instead of sending null")
        return value


class GridPose(FrozenModel):
    """A grid pose: its indices and angles (degrees)."""

    index: GridIndex
    theta_deg: Number
    phi_deg: Number


class PoseEstimate(FrozenModel):
    """The current estimate of the target pose.

    ``grid`` is the grid pose nearest the continuous ``theta_deg``/``phi_deg``;
    ``residual_px`` the reprojection (or layout) residual in camera pixels, null when unknown;
    ``confidence`` in [0, 1] falls with the residual, unmatched detections and ambiguity.
    """

    grid: GridPose
    theta_deg: Number
    phi_deg: Number
    residual_px: Annotated[Number, Field(ge=0.0)] | None
    confidence: Annotated[Number, Field(ge=0.0, le=1.0)]


class CandidatePose(FrozenModel):
    """An alternative pose that explains the target almost as well (lower score is better)."""

    pose: GridPose
    score: Number


class ViewMatch(FrozenModel):
    """How well the current view matches the target, whatever the search decides.

    ``rms_px`` is the RMS box-edge difference over the ``pairs`` (camera pixels; null without
    pairs), ``noise_px`` the RMS difference detection noise alone would give those pairs.
    ``unpaired_current`` / ``unpaired_target`` are the summed confidences of each image's
    detections without a partner. ``score`` in [0, 1] is the paired share of both images'
    confidence times ``exp(−½ (rms / T)²)``, ``T = √((3 t)² + (2 noise)²)`` the loose done
    test's tolerance (``t`` = ``match_rms_px``): 1 for identical views, ≈ 0.61 at that
    tolerance, falling with the box differences and with what stays unpaired. A caller that
    never hears ``done`` can answer with the visited pose that scored best.
    """

    rms_px: Annotated[Number, Field(ge=0.0)] | None
    noise_px: Annotated[Number, Field(ge=0.0)]
    pairs: Annotated[Integer, Field(ge=0)]
    unpaired_current: Annotated[Number, Field(ge=0.0)]
    unpaired_target: Annotated[Number, Field(ge=0.0)]
    score: Annotated[Number, Field(ge=0.0, le=1.0)]


class NextPoseResponse(FrozenModel):
    """``POST /next-pose``: where to go next and whether the search is done.

    ``done`` is decided from the detections alone; when it is true ``next`` is the current pose.
    ``stuck`` is true when the proposed pose has been visited three times already: the strategy
    is going round in circles and the caller should stop or switch strategy. ``match`` says
    how well the current view matches the target (null before the first view).
    """

    strategy: StrategyName
    done: bool
    stuck: bool
    next: GridPose
    move: Move
    estimate: PoseEstimate | None
    ambiguous: bool
    alternatives: tuple[CandidatePose, ...]
    reason: str
    match: ViewMatch | None = None


class MapRequest(FrozenModel):
    """``POST /map``: ground positions of detections seen from a known pose."""

    camera: CameraSpec
    pose: Pose
    method: MappingMethod = "exact"
    view: ImageDetections


class MappedObject(FrozenModel):
    """One detection mapped to the ground (scene units).

    ``offset`` is the camera-relative ground offset ``(towards the camera, to the image's
    right)``; ``position`` its rotation by φ (paper eq. 7). ``radius`` (footprint half-width)
    and ``height`` come from the exact method only. Null values could not be determined.
    """

    label: str
    position: tuple[Number, Number] | None
    offset: tuple[Number, Number] | None
    radius: Number | None
    height: Number | None
    sigma: Annotated[Number, Field(ge=0.0)] | None = Field(
        description="Positional standard deviation for 1-pixel box errors (exact method)."
    )
    reliable: bool


class MapResponse(FrozenModel):
    """``POST /map``: one mapped object per detection, in order."""

    method: MappingMethod
    pose: Pose
    objects: tuple[MappedObject, ...]


class StrategyInfo(FrozenModel):
    """One entry of ``GET /strategies``."""

    name: StrategyName
    description: str
    default: bool
    needs_calibration: bool


class TargetCacheStats(FrozenModel):
    """What the optimizer keeps of free searches' targets between their renders: the
    ``targets`` kept, their ``bytes`` (grey images and distance maps) within ``max_bytes``, and
    since it started the lookups of a target that found it kept (``hits``) or made it
    (``misses``). With several replicas, a search's tasks going to the one that keeps its
    target show as hits there."""

    targets: Annotated[Integer, Field(ge=0)]
    bytes: Annotated[Integer, Field(ge=0)]
    max_bytes: Annotated[Integer, Field(ge=0)]
    hits: Annotated[Integer, Field(ge=0)]
    misses: Annotated[Integer, Field(ge=0)]


class OptimizerHealth(FrozenModel):
    """``GET /health`` of the optimizer."""

    status: Literal["ok"]
    service: Literal["optimizer"]
    strategies: tuple[StrategyName, ...]
    default_strategy: StrategyName
    paper_calibrations: Annotated[Integer, Field(ge=0)]
    target_cache: TargetCacheStats | None = None
    """Null from an optimizer that does not say."""
