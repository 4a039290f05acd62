"""Messages of the renderer service: render requests, per-object annotations, scenes, health."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, field_serializer, field_validator

from services.common.base import BoxXYXY, FrozenModel, Integer, NonNegInt, Number
from services.common.geometry.camera import PinholeCamera
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


class RenderRequest(FrozenModel):
    """``POST /render``: a scene, a pose (continuous or grid indices) and optional film settings."""

    scene: Annotated[str, Field(min_length=1, max_length=128)]
    pose: PoseQuery
    width: Annotated[Integer, Field(ge=8)] | None = None
    height: Annotated[Integer, Field(ge=8)] | None = None
    spp: Annotated[Integer, Field(ge=1)] | None = None
    seed: Annotated[Integer, Field(ge=0, le=2**31 - 1)] = 0


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
    projected_center: tuple[Number, Number] = Field(
        description="Pinhole projection of ``centroid`` in pixels (may lie outside the image)."
    )


class RenderAnnotations(FrozenModel):
    """``POST /render/annotations``: per-object ground truth and the camera of the view."""

    scene: str
    pose: Pose
    grid_index: GridIndex | None
    camera: PinholeCamera
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
