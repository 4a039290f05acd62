"""Messages of the renderer service: render requests, per-object annotations, scenes, health."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, field_serializer, field_validator, model_validator

from services.common.base import BoxXYXY, FrozenModel, Integer, NonNegInt, Number
from services.common.geometry.camera import PinholeCamera
from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.geometry.scene import SceneSpec

__all__ = [
    "ObjectAnnotation",
    "RenderAnnotations",
    "RenderHealth",
    "RenderRequest",
    "SceneDetail",
    "SceneSummary",
]


def _render_request_schema(schema: dict[str, Any]) -> None:
    """Publish that a request gives exactly one of ``pose`` and ``camera``."""
    schema["oneOf"] = [
        {"required": ["pose"], "not": {"required": ["camera"]}},
        {"required": ["camera"], "not": {"required": ["pose"]}},
    ]


class RenderRequest(FrozenModel):
    """``POST /render``: a scene, where the camera is (a hemisphere ``pose``, continuous or grid
    indices, or a free ``camera``: exactly one) and optional film settings.

    ``width`` and ``height`` are the film in pixels (the scene camera's by default; one alone
    keeps its aspect ratio); a free camera's pixel intrinsics are in pixels of that film.
    """

    model_config = ConfigDict(json_schema_extra=_render_request_schema)

    scene: Annotated[str, Field(min_length=1, max_length=128)]
    pose: PoseQuery | None = Field(
        default=None, description="A hemisphere pose: angles or grid indices."
    )
    camera: FreeCamera | None = Field(
        default=None,
        description="A free camera: any position, orientation and intrinsics (instead of pose).",
    )
    width: Annotated[Integer, Field(ge=8)] | None = None
    height: Annotated[Integer, Field(ge=8)] | None = None
    spp: Annotated[Integer, Field(ge=1)] | None = None
    seed: Annotated[Integer, Field(ge=0, le=2**31 - 1)] = 0

    @model_validator(mode="after")
    def _one_camera(self) -> RenderRequest:
        if (self.pose is None) == (self.camera is None):
            raise ValueError("give exactly one of pose and camera")
        return self


class ObjectAnnotation(FrozenModel):
    """Ground truth for one scene object in one rendered view."""

    name: str
    shape: str = Field(description="The object's class: sphere, cube, cylinder, cone or mesh.")
    position: tuple[Number, Number, Number] = Field(
        description="World position of the object's footprint centre on the ground (z = 0)."
    )
    centroid: tuple[Number, Number, Number] = Field(
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
    visible_fraction: Annotated[Number, Field(ge=0.0, le=1.0)]
    projected_center: tuple[Number, Number] | None = Field(
        description="Projection of ``centroid`` in pixels, through the distortion when there is "
        "one (may lie outside the image); null when the centroid is behind the camera (a free "
        "camera can have objects at its back)."
    )


class RenderAnnotations(FrozenModel):
    """``POST /render/annotations``: per-object ground truth and the camera of the view."""

    scene: str
    pose: Pose | None = Field(description="The hemisphere pose; null for a free camera.")
    grid_index: GridIndex | None
    camera: PinholeCamera
    distortion: LensDistortion | None = Field(
        default=None,
        description="The image's lens distortion (OpenCV k1, k2, p1, p2, k3) on top of the pinhole "
        "``camera``; null for a pinhole image. Boxes and projected centres are in the distorted "
        "image.",
    )
    objects: tuple[ObjectAnnotation, ...]


class SceneSummary(FrozenModel):
    """One entry of ``GET /scenes``."""

    id: str
    objects: Integer
    grid_size: Integer
    width: Integer
    height: Integer


class RenderHealth(FrozenModel):
    """``GET /health`` of the renderer."""

    status: Literal["ok"]
    service: Literal["renderer"]
    variant: str
    scenes_loaded: tuple[str, ...]
    scenes_available: Integer
    in_flight: NonNegInt


class SceneDetail(FrozenModel):
    """``GET /scenes/{id}``: a validated scene spec and its hemisphere grid.

    The grid's JSON also lists its ``rings`` and ``size``, for clients that do not compute
    them; read back, they must agree with the step and θ range.
    """

    id: str
    spec: SceneSpec
    grid: GridSpec

    @field_validator("grid", mode="before")
    @classmethod
    def _derived_fields_agree(cls, value: Any) -> Any:
        if not isinstance(value, dict) or not {"rings", "size"} & value.keys():
            return value
        given = {key: value[key] for key in ("rings", "size") if key in value}
        grid = GridSpec.model_validate({k: v for k, v in value.items() if k not in given})
        derived = _grid_json(grid)
        for key, expected in given.items():
            if expected != derived[key]:
                raise ValueError(f"{key} does not follow from the step and θ range")
        return grid

    @field_serializer("grid")
    def _grid_with_rings(self, grid: GridSpec) -> dict[str, Any]:
        return _grid_json(grid)


def _grid_json(grid: GridSpec) -> dict[str, Any]:
    """A grid's parameters with its rings and size, as JSON values."""
    hemisphere = grid.grid()
    return {
        **grid.model_dump(mode="json"),
        "rings": [ring.model_dump(mode="json") for ring in hemisphere.rings],
        "size": hemisphere.size,
    }
