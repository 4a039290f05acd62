"""The scene file format: pydantic models, YAML loading with clear errors, and asset path checks.

A scene is a YAML file whose id is its file stem; its assets (PLY meshes, textures) live in the same
folder. World frame: the ground is the plane z = 0 centred at the origin, +z is up, lengths are in
scene units. An object's ``position`` is its footprint centre on the ground and every object
rests on the ground.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from services.common.base import FrozenModel, Integer, Number
from services.common.geometry.grid import GridSpec

__all__ = [
    "SCENE_ID_PATTERN",
    "CameraSpec",
    "ConeObject",
    "CubeObject",
    "CylinderObject",
    "Ground",
    "Lighting",
    "LoadedScene",
    "MeshObject",
    "PointLight",
    "SceneFileError",
    "SceneObject",
    "SceneSpec",
    "SphereObject",
    "load_scene",
    "parse_scene",
    "scene_json_schema",
]

SCENE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$"
MAX_SCENE_FILE_CHARS = 1_000_000
_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"

# Strict numbers (as a scene file is read): the camera also travels in optimizer requests.
PositiveLength = Annotated[Number, Field(gt=0.0, le=1e4)]
Coordinate = Annotated[Number, Field(ge=-1e4, le=1e4)]
Unit = Annotated[Number, Field(ge=0.0, le=1.0)]
Rgb = tuple[Unit, Unit, Unit]
YawDeg = Annotated[Number, Field(ge=-360.0, le=360.0)]
AssetPath = Annotated[str, Field(min_length=1, max_length=512)]


class CameraSpec(FrozenModel):
    """The perspective camera: horizontal field of view, film size in pixels, hemisphere radius."""

    fov_deg: Annotated[Number, Field(gt=1.0, lt=170.0, description="Horizontal field of view.")]
    width: Annotated[Integer, Field(ge=16, le=4096)]
    height: Annotated[Integer, Field(ge=16, le=4096)]
    radius: PositiveLength


class PointLight(FrozenModel):
    """The paper's point emitter: a world position and a radiant intensity."""

    position: tuple[Coordinate, Coordinate, Coordinate]
    intensity: Annotated[float, Field(gt=0.0, le=1e7, allow_inf_nan=False)]


class Lighting(FrozenModel):
    """A point emitter plus an optional constant environment radiance (ambient)."""

    point: PointLight
    ambient: Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)] = 0.0


class _Surface(FrozenModel):
    """Something with either a linear-RGB ``color`` or a bitmap ``texture`` (not both)."""

    color: Rgb | None = None
    texture: AssetPath | None = None

    @model_validator(mode="after")
    def _one_appearance(self) -> _Surface:
        if self.color is not None and self.texture is not None:
            raise ValueError("give either color or texture, not both")
        return self


class Ground(_Surface):
    """The ground square of side ``size`` centred at the origin in the plane z = 0."""

    size: PositiveLength


class _Object(_Surface):
    name: Annotated[str, Field(pattern=_NAME_PATTERN)]
    position: tuple[Coordinate, Coordinate]


class SphereObject(_Object):
    """A sphere of ``radius`` resting on the ground."""

    shape: Literal["sphere"]
    radius: PositiveLength


class CubeObject(_Object):
    """A cube of edge ``size`` resting on the ground, turned by ``yaw_deg`` about +z."""

    shape: Literal["cube"]
    size: PositiveLength
    yaw_deg: YawDeg = 0.0


class CylinderObject(_Object):
    """An upright capped cylinder of ``radius`` and ``height`` standing on the ground."""

    shape: Literal["cylinder"]
    radius: PositiveLength
    height: PositiveLength
    yaw_deg: YawDeg = 0.0


class ConeObject(_Object):
    """An upright cone of base ``radius`` and ``height`` standing on the ground."""

    shape: Literal["cone"]
    radius: PositiveLength
    height: PositiveLength
    yaw_deg: YawDeg = 0.0


class MeshObject(_Object):
    """A PLY mesh, scaled by ``scale`` and turned by ``yaw_deg``; the renderer moves its bounding
    box's bottom centre to ``position`` on the ground."""

    shape: Literal["mesh"]
    file: AssetPath
    scale: PositiveLength = 1.0
    yaw_deg: YawDeg = 0.0


SceneObject = Annotated[
    SphereObject | CubeObject | CylinderObject | ConeObject | MeshObject,
    Field(discriminator="shape"),
]


class SceneSpec(FrozenModel):
    """A whole scene file."""

    camera: CameraSpec
    lighting: Lighting
    ground: Ground
    objects: Annotated[list[SceneObject], Field(min_length=1, max_length=64)]
    search: GridSpec = GridSpec()

    @field_validator("objects")
    @classmethod
    def _unique_names(cls, objects: list[SceneObject]) -> list[SceneObject]:
        seen: set[str] = set()
        for obj in objects:
            if obj.name in seen:
                raise ValueError(f"object name {obj.name!r} is used twice")
            seen.add(obj.name)
        return objects

    @model_validator(mode="after")
    def _objects_on_ground(self) -> SceneSpec:
        half = self.ground.size / 2.0
        for i, obj in enumerate(self.objects):
            x, y = obj.position
            if abs(x) > half or abs(y) > half:
                raise _layout_error(
                    f"objects[{i}].position",
                    f"{obj.name} stands at {obj.position}, off the ground square of size "
                    f"{self.ground.size}",
                )
        extent = _scene_extent(self)
        if self.camera.radius <= extent:
            raise _layout_error(
                "camera.radius",
                f"{self.camera.radius} does not clear the objects (they reach {extent:.3g} "
                "from the centre)",
            )
        return self

    def asset_paths(self) -> dict[str, str]:
        """Every asset the scene refers to, keyed by the field that names it."""
        assets: dict[str, str] = {}
        if self.ground.texture is not None:
            assets["ground.texture"] = self.ground.texture
        for i, obj in enumerate(self.objects):
            if obj.texture is not None:
                assets[f"objects[{i}].texture"] = obj.texture
            if isinstance(obj, MeshObject):
                assets[f"objects[{i}].file"] = obj.file
        return assets


def _layout_error(field: str, message: str) -> PydanticCustomError:
    """A whole-scene check's error that still names its field (``ctx["field"]``)."""
    return PydanticCustomError(
        "scene_layout", "{field}: {message}", {"field": field, "message": message}
    )


def _scene_extent(spec: SceneSpec) -> float:
    """A loose bound on how far any primitive reaches from the origin (meshes are not measured)."""
    extent = 0.0
    for obj in spec.objects:
        reach = math.hypot(*obj.position)
        if isinstance(obj, SphereObject):
            extent = max(extent, math.hypot(reach + obj.radius, 2 * obj.radius))
        elif isinstance(obj, CubeObject):
            extent = max(extent, math.hypot(reach + obj.size, obj.size))
        elif isinstance(obj, CylinderObject | ConeObject):
            extent = max(extent, math.hypot(reach + obj.radius, obj.height))
        else:
            extent = max(extent, reach)
    return extent


class SceneFileError(ValueError):
    """A scene file that cannot be used; the message names the file and the offending field."""

    def __init__(self, path: Path | str, field: str | None, message: str) -> None:
        self.path = str(path)
        self.field = field
        self.message = message
        where = f"{self.path}: {field}: " if field else f"{self.path}: "
        super().__init__(where + message)


@dataclass(frozen=True)
class LoadedScene:
    """A validated scene: its id, its file, the spec and its assets resolved on disk."""

    id: str
    path: Path
    spec: SceneSpec
    assets: dict[str, Path]
    version: int = 0
    """The file's modification time in ns: a changed file is a new version."""

    @property
    def directory(self) -> Path:
        return self.path.parent


_SHAPE_TAGS = frozenset({"sphere", "cube", "cylinder", "cone", "mesh"})


def _field_name(loc: tuple[int | str, ...]) -> str:
    """Turn a pydantic error location into a dotted path such as ``objects[3].radius``.

    Discriminated unions insert the tag (``sphere``) into the location; it is dropped here.
    """
    out = ""
    for position, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in _SHAPE_TAGS and position > 0 and isinstance(loc[position - 1], int):
            continue  # the union's tag, right after the list index
        else:
            out += ("." if out else "") + part
    return out or "(root)"


def resolve_asset(scene_dir: Path, relative: str, field: str, scene_path: Path) -> Path:
    """Resolve an asset path inside ``scene_dir``, refusing anything that would leave it.

    Absolute paths, ``..`` components and symlinks pointing outside the folder are rejected, and
    the file must exist.
    """
    candidate = Path(relative)
    if (
        candidate.is_absolute()
        or relative.startswith(("/", "\\"))
        or re.match(r"^[A-Za-z]:", relative)
    ):
        raise SceneFileError(scene_path, field, f"asset path {relative!r} must be relative")
    if ".." in candidate.parts or "\\" in relative:
        raise SceneFileError(
            scene_path, field, f"asset path {relative!r} must stay inside the scene's folder"
        )
    try:
        root = scene_dir.resolve()
        resolved = (scene_dir / candidate).resolve()
        inside = resolved.is_relative_to(root)
        exists = inside and resolved.is_file()
    except (OSError, RuntimeError, ValueError) as exc:  # loops, NUL bytes, over-long names
        raise SceneFileError(
            scene_path, field, f"asset path {relative!r} is unusable ({exc})"
        ) from exc
    if not inside:
        raise SceneFileError(
            scene_path, field, f"asset path {relative!r} leads outside the scene's folder"
        )
    if not exists:
        raise SceneFileError(scene_path, field, f"asset file {relative!r} does not exist")
    return resolved


class _SceneLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a key given twice in one mapping is an error, not "last wins"."""


def _unique_mapping(loader: _SceneLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        if isinstance(key, str) and key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        seen.add(key if isinstance(key, str) else id(key))
    return loader.construct_mapping(node, deep=deep)


_SceneLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def parse_scene(text: str, path: Path) -> SceneSpec:
    """Parse and validate scene YAML ``text``; errors name ``path`` and the field."""
    if len(text) > MAX_SCENE_FILE_CHARS:
        raise SceneFileError(path, None, f"larger than {MAX_SCENE_FILE_CHARS} characters")
    try:
        data: Any = yaml.load(text, Loader=_SceneLoader)  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else None
        raise SceneFileError(
            path, where, f"not valid YAML ({getattr(exc, 'problem', exc)})"
        ) from exc
    except (ValueError, TypeError, LookupError, AttributeError, RecursionError) as exc:
        # PyYAML's constructors raise plain Python errors for bad tagged scalars (!!int abc).
        raise SceneFileError(path, None, f"not valid YAML ({type(exc).__name__}: {exc})") from exc
    if not isinstance(data, dict):
        raise SceneFileError(path, None, "a scene file must be a YAML mapping")
    try:
        # Strict, as the published JSON Schema: no '45' for a number, no 320.5 for a width.
        # JSON mode, so that YAML sequences stand for tuples as JSON arrays do.
        document = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError) as exc:  # a YAML date, set or binary: no JSON counterpart
        raise SceneFileError(path, None, f"not a JSON-compatible document ({exc})") from exc
    try:
        return SceneSpec.model_validate_json(document, strict=True)
    except ValidationError as exc:
        first = exc.errors()[0]
        more = len(exc.errors()) - 1
        suffix = f" (and {more} more error{'s' if more > 1 else ''})" if more else ""
        message = first["msg"]
        field = _field_name(tuple(first["loc"]))
        if first["type"] == "extra_forbidden":
            message = "unknown key"
        elif first["type"] == "scene_layout":
            field, message = first["ctx"]["field"], first["ctx"]["message"]
        raise SceneFileError(path, field, message + suffix) from exc


def load_scene(path: Path) -> LoadedScene:
    """Read, validate and resolve the scene file at ``path`` (id = file stem)."""
    scene_id = path.stem
    if re.match(SCENE_ID_PATTERN, scene_id) is None:
        raise SceneFileError(path, None, f"scene id {scene_id!r} (the file stem) is not allowed")
    try:
        text = path.read_text(encoding="utf-8")
        version = path.stat().st_mtime_ns
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFileError(path, None, f"cannot read the file ({exc})") from exc
    spec = parse_scene(text, path)
    assets = {
        field: resolve_asset(path.parent, relative, field, path)
        for field, relative in spec.asset_paths().items()
    }
    return LoadedScene(id=scene_id, path=path, spec=spec, assets=assets, version=version)


def scene_json_schema() -> dict[str, Any]:
    """The JSON Schema of the scene format (published by the renderer and in ``docs/``)."""
    schema = SceneSpec.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "COSMOS 3D Search scene"
    return schema
