"""Scene files: the README example, built-in scenes, errors naming fields, asset paths, schema."""

from __future__ import annotations

import datetime
import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hypothesis
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from services.common.geometry.grid import GridSpec, HemisphereGrid
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    MeshObject,
    SceneFileError,
    SceneSpec,
    SphereObject,
    load_scene,
    parse_scene,
    resolve_asset,
    scene_json_schema,
)
from tools.export_schema import SCHEMA_PATH, main, render_schema

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes"
BUILTIN = ("demo", "garden")
PATH = Path("/srv/scenes/example.yaml")  # parse_scene only uses it in messages

EXAMPLE_YAML = """\
camera: {fov_deg: 45, width: 320, height: 240, radius: 8.0}   # fov is horizontal
lighting:
  point: {position: [3.0, 3.0, 8.0], intensity: 200.0}       # the paper's point emitter
  ambient: 0.2                                                # optional constant environment
ground: {size: 12.0, color: [0.5, 0.5, 0.5]}                  # or texture: textures/tiles.png
objects:
  - {name: red, shape: sphere, position: [1.0, -0.5], radius: 0.4, color: [0.9, 0.1, 0.1]}
  - {name: crate, shape: cube, position: [-1.5, 1.0], size: 0.6, yaw_deg: 20, color: [0.2, 0.3, 0.9]}
  - {name: post, shape: cylinder, position: [0.5, 2.0], radius: 0.25, height: 0.9, color: [0.1, 0.8, 0.2]}
  - {name: duck, shape: mesh, file: meshes/duck.ply, position: [-2.0, -1.5], scale: 0.5, yaw_deg: 90, texture: textures/duck.png}
search: {angle_step_deg: 7.5, min_theta_deg: 7.5, max_theta_deg: 82.5}
"""  # noqa: E501 (the README's lines, verbatim)


def example() -> dict[str, Any]:
    """A fresh, mutable copy of the README example as plain data."""
    data: dict[str, Any] = yaml.safe_load(EXAMPLE_YAML)
    return data


def test_the_readme_shows_the_example_verbatim():
    assert EXAMPLE_YAML in (ROOT / "README.md").read_text()


def dump(data: Any) -> str:
    return yaml.safe_dump(data, sort_keys=False)


def parse(data: Any) -> SceneSpec:
    return parse_scene(dump(data), PATH)


def rejection(data: Any) -> SceneFileError:
    with pytest.raises(SceneFileError) as info:
        parse(data)
    return info.value


def set_at(data: Any, path: tuple[str | int, ...], value: Any) -> Any:
    """``data`` with the value at ``path`` replaced (or a new key added)."""
    *parents, last = path
    node = data
    for part in parents:
        node = node[part]
    node[last] = value
    return data


def delete_at(data: Any, path: tuple[str | int, ...]) -> Any:
    *parents, last = path
    node = data
    for part in parents:
        node = node[part]
    del node[last]
    return data


def all_paths(node: Any, prefix: tuple[str | int, ...] = ()) -> list[tuple[str | int, ...]]:
    """Every path into nested dicts and lists, containers included."""
    found = [prefix] if prefix else []
    if isinstance(node, dict):
        for key, value in node.items():
            found += all_paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            found += all_paths(value, (*prefix, i))
    return found


def copy_example_assets(folder: Path) -> None:
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(SCENES / "meshes" / "duck.ply", folder / "meshes" / "duck.ply")
    shutil.copyfile(SCENES / "textures" / "duck.png", folder / "textures" / "duck.png")


@pytest.fixture
def example_dir(tmp_path: Path) -> Path:
    """A scene folder holding ``example.yaml`` (the README example) and its two assets."""
    copy_example_assets(tmp_path)
    (tmp_path / "example.yaml").write_text(EXAMPLE_YAML, encoding="utf-8")
    return tmp_path


def write_scene(folder: Path, data: Any, stem: str = "example") -> Path:
    path = folder / f"{stem}.yaml"
    path.write_text(dump(data), encoding="utf-8")
    return path


# -- valid scenes ------------------------------------------------------------------------------


def test_readme_example_loads_with_its_values(example_dir):
    path = example_dir / "example.yaml"
    scene = load_scene(path)
    spec = scene.spec

    assert scene.id == "example"
    assert scene.path == path
    assert scene.directory == example_dir
    assert scene.version == path.stat().st_mtime_ns
    assert (spec.camera.fov_deg, spec.camera.width, spec.camera.height) == (45.0, 320, 240)
    assert spec.camera.radius == 8.0
    assert spec.lighting.point.position == (3.0, 3.0, 8.0)
    assert spec.lighting.point.intensity == 200.0
    assert spec.lighting.ambient == 0.2
    assert spec.ground.size == 12.0
    assert spec.ground.color == (0.5, 0.5, 0.5)
    assert spec.ground.texture is None

    red, crate, post, duck = spec.objects
    assert isinstance(red, SphereObject)
    assert (red.name, red.position, red.radius, red.color) == (
        "red",
        (1.0, -0.5),
        0.4,
        (0.9, 0.1, 0.1),
    )
    assert isinstance(crate, CubeObject)
    assert (crate.name, crate.position, crate.size, crate.yaw_deg) == (
        "crate",
        (-1.5, 1.0),
        0.6,
        20,
    )
    assert crate.color == (0.2, 0.3, 0.9)
    assert isinstance(post, CylinderObject)
    assert (post.position, post.radius, post.height, post.yaw_deg) == ((0.5, 2.0), 0.25, 0.9, 0.0)
    assert isinstance(duck, MeshObject)
    assert (duck.file, duck.position, duck.scale, duck.yaw_deg) == (
        "meshes/duck.ply",
        (-2.0, -1.5),
        0.5,
        90.0,
    )
    assert (duck.texture, duck.color) == ("textures/duck.png", None)

    search = spec.search
    assert (search.angle_step_deg, search.min_theta_deg, search.max_theta_deg) == (7.5, 7.5, 82.5)
    assert scene.assets == {
        "objects[3].file": (example_dir / "meshes" / "duck.ply").resolve(),
        "objects[3].texture": (example_dir / "textures" / "duck.png").resolve(),
    }


def test_omitted_optional_fields_take_their_defaults():
    data = example()
    del data["lighting"]["ambient"]
    del data["search"]
    del data["objects"][1]["yaw_deg"]
    del data["objects"][3]["scale"]
    del data["objects"][3]["yaw_deg"]
    spec = parse(data)
    assert spec.lighting.ambient == 0.0
    assert spec.search == GridSpec(angle_step_deg=7.5, min_theta_deg=0.0, max_theta_deg=90.0)
    assert spec.objects[1].yaw_deg == 0.0  # type: ignore[union-attr]
    assert spec.objects[3].scale == 1.0  # type: ignore[union-attr]
    assert spec.objects[3].yaw_deg == 0.0  # type: ignore[union-attr]


def test_every_shape_including_the_cone_is_accepted():
    data = example()
    data["objects"].append(
        {"name": "hat", "shape": "cone", "position": [2.0, 1.0], "radius": 0.3, "height": 0.8}
    )
    spec = parse(data)
    assert [type(o) for o in spec.objects] == [
        SphereObject,
        CubeObject,
        CylinderObject,
        MeshObject,
        ConeObject,
    ]


def test_specs_are_frozen():
    spec = parse(example())
    with pytest.raises(ValidationError):
        spec.camera.radius = 1.0  # type: ignore[misc]


@pytest.mark.parametrize("scene_id", BUILTIN)
def test_builtin_scene_loads(scene_id):
    scene = load_scene(SCENES / f"{scene_id}.yaml")
    assert scene.id == scene_id
    assert scene.directory == SCENES
    assert len(scene.spec.objects) >= 5
    for field, asset in scene.assets.items():
        assert asset.is_file(), field
        assert asset.is_relative_to(SCENES.resolve()), field
    assert set(scene.assets) == set(scene.spec.asset_paths())


def test_garden_uses_every_shape_and_all_its_assets():
    scene = load_scene(SCENES / "garden.yaml")
    assert {o.shape for o in scene.spec.objects} == {"sphere", "cube", "cylinder", "cone", "mesh"}
    assert {p.relative_to(SCENES.resolve()).as_posix() for p in scene.assets.values()} == {
        "textures/tiles.png",
        "textures/wood.png",
        "textures/duck.png",
        "meshes/duck.ply",
        "meshes/arch.ply",
    }
    assert scene.assets["ground.texture"] == (SCENES / "textures" / "tiles.png").resolve()


# -- errors name the field and the file ----------------------------------------------------------

DELETE = object()
"""Stands for "remove this key" in the tables below."""

FIELD_ERRORS: list[tuple[tuple[str | int, ...], Any, str, str]] = [
    # (path edited, new value or DELETE, field the error names, words in its message)
    (("objects", 2, "radius"), -1, "objects[2].radius", "greater than 0"),
    (("camera", "fov_deg"), 180, "camera.fov_deg", "less than 170"),
    (("camera", "fov_deg"), DELETE, "camera.fov_deg", "required"),
    (("objects", 0, "colour"), [1, 0, 0], "objects[0].colour", "unknown key"),
    (("camera", "width"), 8, "camera.width", "16"),
    (("camera", "height"), 240.5, "camera.height", "integer"),
    (("ground", "color"), [0.5, 0.5], "ground.color[2]", "required"),
    (("objects", 1, "color", 2), 1.5, "objects[1].color[2]", "less than or equal to 1"),
    (("lighting", "point", "position", 2), "high", "lighting.point.position[2]", "number"),
    (("lighting", "point", "intensity"), 0, "lighting.point.intensity", "greater than 0"),
    (("objects", 3, "scale"), 0, "objects[3].scale", "greater than 0"),
    (("objects", 1, "name"), "my crate", "objects[1].name", "pattern"),
    (("objects", 2, "yaw_deg"), 400, "objects[2].yaw_deg", "360"),
    (("objects",), [], "objects", "at least 1"),
    (("objects", 3, "file"), DELETE, "objects[3].file", "required"),
    (("search", "angle_step_deg"), 91, "search.angle_step_deg", "90"),
    (("search",), [7.5], "search", "object"),
    # strict, like the published JSON Schema: no strings for numbers, no fractions for counts
    (("camera", "fov_deg"), "45", "camera.fov_deg", "number"),
    (("camera", "width"), "320", "camera.width", "integer"),
    (("camera", "width"), 320.0, "camera.width", "integer"),
    (("objects", 0, "color", 0), "1", "objects[0].color[0]", "number"),
    (("lighting",), DELETE, "lighting", "required"),
]


def edit(data: Any, path: tuple[str | int, ...], value: Any) -> Any:
    return delete_at(data, path) if value is DELETE else set_at(data, path, value)


@pytest.mark.parametrize(
    ("path", "value", "field", "fragment"),
    FIELD_ERRORS,
    ids=[f"{f}-{'deleted' if v is DELETE else 'bad'}" for _, v, f, _ in FIELD_ERRORS],
)
def test_error_names_the_field_and_the_file(path, value, field, fragment):
    error = rejection(edit(example(), path, value))
    assert error.field == field
    assert error.path == str(PATH)
    assert str(error).startswith(f"{PATH}: {field}: ")
    assert fragment.lower() in error.message.lower()


def test_yaml_values_without_a_json_counterpart_are_refused():
    data = example()
    data["camera"]["fov_deg"] = datetime.date(2020, 1, 1)
    error = rejection(data)
    assert "json" in error.message.lower()


def test_load_scene_errors_name_the_real_file(example_dir):
    data = example()
    data["objects"][2]["radius"] = -1
    path = write_scene(example_dir, data, "broken")
    with pytest.raises(SceneFileError) as info:
        load_scene(path)
    assert info.value.path == str(path)
    assert info.value.field == "objects[2].radius"
    assert str(info.value).startswith(f"{path}: objects[2].radius: ")


def test_error_counts_the_errors_it_does_not_show():
    data = example()
    data["camera"]["fov_deg"] = 0
    assert "more error" not in rejection(data).message
    data["camera"]["width"] = 0
    assert rejection(data).message.endswith("(and 1 more error)")
    data["camera"]["height"] = 0
    assert rejection(data).message.endswith("(and 2 more errors)")


UNKNOWN_KEY_PATHS: list[tuple[tuple[str | int, ...], str]] = [
    (("extra",), "extra"),
    (("camera", "focal"), "camera.focal"),
    (("lighting", "spot"), "lighting.spot"),
    (("lighting", "point", "color"), "lighting.point.color"),
    (("ground", "height"), "ground.height"),
    (("objects", 0, "size"), "objects[0].size"),  # a cube's key on a sphere
    (("objects", 1, "radius"), "objects[1].radius"),  # a sphere's key on a cube
    (("objects", 2, "scale"), "objects[2].scale"),
    (("objects", 3, "colour"), "objects[3].colour"),
    (("search", "step_deg"), "search.step_deg"),
]


@pytest.mark.parametrize(
    ("path", "field"), UNKNOWN_KEY_PATHS, ids=[f for _, f in UNKNOWN_KEY_PATHS]
)
def test_unknown_keys_are_errors_at_every_level(path, field):
    error = rejection(set_at(example(), path, 1))
    assert (error.field, error.message) == (field, "unknown key")


@pytest.mark.parametrize(
    ("path", "field"),
    [
        (("objects", 3, "mesh"), "objects[3].mesh"),  # a plausible slip for `file:`
        (("objects", 0, "sphere"), "objects[0].sphere"),
        (("objects", 1, "cylinder"), "objects[1].cylinder"),
        (("ground", "cone"), "ground.cone"),
        (("cube",), "cube"),
    ],
)
def test_unknown_key_named_like_a_shape_is_named(path, field):
    error = rejection(set_at(example(), path, "meshes/duck.ply"))
    assert (error.field, error.message) == (field, "unknown key")


# -- semantic checks ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("path", "field"),
    [(("objects", 0), "objects[0]"), (("objects", 3), "objects[3]"), (("ground",), "ground")],
)
def test_color_and_texture_together_are_rejected(path, field):
    data = example()
    node = data
    for part in path:
        node = node[part]
    node["color"] = [0.5, 0.5, 0.5]
    node["texture"] = "textures/duck.png"
    error = rejection(data)
    assert error.field == field
    assert "either color or texture" in error.message


@pytest.mark.parametrize("shape", ["torus", "Sphere", "", 3, ["sphere"], None])
def test_unknown_shape_is_rejected(shape):
    error = rejection(set_at(example(), ("objects", 0, "shape"), shape))
    assert error.field == "objects[0]"
    assert "'sphere', 'cube', 'cylinder', 'cone', 'mesh'" in error.message


def test_missing_shape_is_rejected():
    error = rejection(delete_at(example(), ("objects", 1, "shape")))
    assert error.field == "objects[1]"
    assert "shape" in error.message


def test_duplicate_object_names_are_rejected():
    error = rejection(set_at(example(), ("objects", 2, "name"), "red"))
    assert error.field == "objects"
    assert "'red' is used twice" in error.message


@pytest.mark.parametrize("position", [[6.5, 0.0], [0.0, -6.01], [-7.0, 7.0], [100.0, 0.0]])
def test_object_off_the_ground_is_rejected(position):
    error = rejection(set_at(example(), ("objects", 1, "position"), position))
    assert error.field == "objects[1].position"
    assert "crate stands at" in error.message
    assert "off the ground" in error.message


@pytest.mark.parametrize("position", [[6.0, 0.0], [-6.0, 6.0], [0.0, -5.99]])
def test_object_on_the_ground_edge_is_accepted(position):
    data = set_at(example(), ("objects", 0, "position"), position)
    data["camera"]["radius"] = 20.0
    assert parse(data).objects[0].position == tuple(position)


@pytest.mark.parametrize("radius", [0.5, 2.0, 2.5])
def test_camera_radius_inside_the_objects_is_rejected(radius):
    # The objects reach 2.5 from the centre (the duck; the primitives stay just inside that).
    error = rejection(set_at(example(), ("camera", "radius"), radius))
    assert error.field == "camera.radius"
    assert f"{radius} does not clear the objects" in error.message


def test_camera_radius_must_clear_a_tall_object():
    data = example()
    data["objects"] = [
        {"name": "tower", "shape": "cylinder", "position": [0, 0], "radius": 0.1, "height": 5.0}
    ]
    data["camera"]["radius"] = 4.0  # outside the footprint but below the top
    assert "does not clear" in rejection(data).message
    data["camera"]["radius"] = 5.5
    assert parse(data).camera.radius == 5.5


def test_min_theta_above_max_theta_is_rejected():
    error = rejection(set_at(example(), ("search",), {"min_theta_deg": 60, "max_theta_deg": 30}))
    assert error.field == "search"
    assert "min_theta_deg must not exceed max_theta_deg" in error.message


@pytest.mark.parametrize(
    ("step", "lo", "hi"), [(30.0, 35.0, 55.0), (7.5, 8.0, 14.9), (90.0, 1.0, 89.0)]
)
def test_theta_range_without_a_ring_is_rejected(step, lo, hi):
    search = {"angle_step_deg": step, "min_theta_deg": lo, "max_theta_deg": hi}
    error = rejection(set_at(example(), ("search",), search))
    assert error.field == "search"
    assert "no ring" in error.message


@pytest.mark.parametrize(
    ("step", "lo", "hi"), [(30.0, 30.0, 30.0), (7.5, 0.0, 0.0), (0.1, 0.3, 0.3)]
)
def test_theta_range_holding_exactly_one_ring_is_accepted(step, lo, hi):
    search = {"angle_step_deg": step, "min_theta_deg": lo, "max_theta_deg": hi}
    spec = parse(set_at(example(), ("search",), search))
    assert HemisphereGrid(step, lo, hi).ring_count == 1
    assert spec.search.min_theta_deg == lo


def _settings_ok(step: float, lo: float, hi: float) -> bool:
    try:
        GridSpec(angle_step_deg=step, min_theta_deg=lo, max_theta_deg=hi)
    except ValidationError:
        return False
    return True


def _grid_ok(step: float, lo: float, hi: float) -> bool:
    try:
        HemisphereGrid(step, lo, hi)
    except ValueError:
        return False
    return True


@settings(max_examples=150, deadline=None)
@given(
    step=st.sampled_from([0.5, 2.5, 7.5, 10.0, 13.0, 22.5, 30.0, 45.0, 90.0]),
    lo=st.integers(0, 180).map(lambda k: k / 2),
    hi=st.integers(0, 180).map(lambda k: k / 2),
)
def test_search_settings_accept_exactly_the_grids_that_can_be_built(step, lo, hi):
    assert _settings_ok(step, lo, hi) == _grid_ok(step, lo, hi)


def test_search_step_too_fine_for_a_grid_is_rejected():
    # 0.001° would mean some 2·10^10 grid poses: the scene must fail to load, not its grid later.
    assert not _grid_ok(0.001, 0.0, 90.0)
    error = rejection(set_at(example(), ("search", "angle_step_deg"), 0.001))
    assert error.field == "search"
    assert "grid poses" in error.message


def test_search_settings_and_grid_share_the_ring_tolerance():
    # Just above the pole by more than the grid's 1e-9° but less than 1e-9 of the step.
    step, lo, hi = 85.19035577839438, 5.960464477539063e-08, 1e-06
    assert not _grid_ok(step, lo, hi)
    assert not _settings_ok(step, lo, hi)


NON_FINITE: list[tuple[tuple[str | int, ...], str]] = [
    (("camera", "fov_deg"), "camera.fov_deg"),
    (("camera", "radius"), "camera.radius"),
    (("lighting", "point", "position", 0), "lighting.point.position[0]"),
    (("lighting", "point", "intensity"), "lighting.point.intensity"),
    (("lighting", "ambient"), "lighting.ambient"),
    (("ground", "size"), "ground.size"),
    (("ground", "color", 1), "ground.color[1]"),
    (("objects", 0, "radius"), "objects[0].radius"),
    (("objects", 1, "position", 1), "objects[1].position[1]"),
    (("objects", 1, "yaw_deg"), "objects[1].yaw_deg"),
    (("objects", 2, "height"), "objects[2].height"),
    (("objects", 3, "scale"), "objects[3].scale"),
    (("search", "angle_step_deg"), "search.angle_step_deg"),
    (("search", "max_theta_deg"), "search.max_theta_deg"),
]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize(("path", "field"), NON_FINITE, ids=[f for _, f in NON_FINITE])
def test_non_finite_numbers_are_rejected(path, field, value):
    text = dump(set_at(example(), path, value))
    assert ".nan" in text.lower() or ".inf" in text.lower()
    with pytest.raises(SceneFileError) as info:
        parse_scene(text, PATH)
    assert info.value.field == field


# -- YAML-level errors -------------------------------------------------------------------------


def test_invalid_yaml_error_gives_the_line():
    text = EXAMPLE_YAML.replace("ground: {size: 12.0,", "ground: {size: 12.0,,")
    with pytest.raises(SceneFileError) as info:
        parse_scene(text, PATH)
    assert info.value.field is not None
    assert info.value.field.startswith("line 5, column ")
    assert "not valid YAML" in info.value.message
    assert str(info.value).startswith(f"{PATH}: line 5, column ")


def test_yaml_tab_indentation_error_gives_the_line():
    with pytest.raises(SceneFileError) as info:
        parse_scene("camera:\n  fov_deg: 45\n\twidth: 320\n", PATH)
    assert info.value.field is not None
    assert info.value.field.startswith("line 3")


@pytest.mark.parametrize(
    "text", ["", "# only a comment\n", "null", "- camera\n- lighting\n", "42", "scene", "[]"]
)
def test_non_mapping_yaml_is_rejected(text):
    with pytest.raises(SceneFileError) as info:
        parse_scene(text, PATH)
    assert info.value.field is None
    assert info.value.message == "a scene file must be a YAML mapping"
    assert str(info.value) == f"{PATH}: a scene file must be a YAML mapping"


def test_oversized_file_is_rejected_before_parsing():
    text = EXAMPLE_YAML + "#" * 1_000_000
    with pytest.raises(SceneFileError) as info:
        parse_scene(text, PATH)
    assert info.value.field is None
    assert "characters" in info.value.message
    assert isinstance(parse_scene(EXAMPLE_YAML + "#" * 1000, PATH), SceneSpec)


MALFORMED = [
    "camera: [",
    "camera: {fov_deg: 45",
    "objects: - a",
    "key: 'unterminated",
    "a: b: c",
    "? [a, b]\n: 1",
    "camera: !!python/object:os.system {}",
    "camera: !!python/name:os.system",
    "camera: !custom 1",
    "camera: !!set [1]",
    "camera: !!omap {a: 1}",
    "camera: !!str [1]",
    "camera: !!binary '%%%'",
    "camera: *undefined",
    "&r {camera: *r}",
    "objects: &x [*x]",
    "\x00camera: 1",
    "camera: \x07",
    "\ufeffcamera: 1",
    "camera: {~: 1}",
    "camera: {1.5: 1}",
    "camera: {[1]: 1}",
    "1: 2",
    "~: 3",
    "camera: 2020-01-01",
    "objects: [null, 1, 'x', []]",
    "objects: {name: red}",
    "camera: {fov_deg: '45', width: '3x', height: 240, radius: 8}",
    "camera: {fov_deg: 1e999, width: 320, height: 240, radius: 8}",
    "camera: {fov_deg: 45, width: 1" + "0" * 300 + ", height: 240, radius: 8}",
    "search: {angle_step_deg: 0}",
    # PyYAML's constructors raise plain ValueError/IndexError/KeyError/AttributeError here.
    "camera: !!int abc",
    "camera: !!int 0x",
    "camera: !!int ''",
    "camera: !!float abc",
    "camera: !!float ''",
    "camera: !!bool maybe",
    "camera: !!timestamp abc",
    "camera: !!timestamp 2020-13-45",
    "camera: {width: 1" + "0" * 5000 + "}",
    "objects: " + "[" * 1000 + "]" * 1000,  # PyYAML composes recursively
    "camera: " + "{a: " * 1000 + "}" * 1000,
]


@pytest.mark.parametrize(
    "text", [pytest.param(t, id=t[:30]) if isinstance(t, str) else t for t in MALFORMED]
)
def test_malformed_input_raises_only_scene_file_error(text):
    with pytest.raises(SceneFileError) as info:
        parse_scene(text, PATH)
    assert info.value.path == str(PATH)
    assert str(info.value).startswith(f"{PATH}: ")


# Values of every kind YAML can carry, nested a little.
yaml_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats()
    | st.text(max_size=8)
    | st.sampled_from(["sphere", "cube", "cylinder", "cone", "mesh", "textures/duck.png"]),
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(
            st.text(max_size=6) | st.sampled_from(["name", "shape", "color", "texture", "radius"]),
            children,
            max_size=4,
        )
    ),
    max_leaves=8,
)
EXAMPLE_PATHS = all_paths(example())


def _get(data: Any, path: tuple[str | int, ...]) -> Any:
    for part in path:
        data = data[part]
    return data


@st.composite
def mutated_examples(draw: st.DrawFn) -> Any:
    """The README example with a few random edits: replaced values, new keys, deleted keys."""
    data = example()
    known_keys = sorted({str(p[-1]) for p in EXAMPLE_PATHS})
    for _ in range(draw(st.integers(1, 3))):
        paths = all_paths(data)
        action = draw(st.sampled_from(["replace", "add", "delete"]))
        if action == "add" or not paths:
            mappings = [p for p in paths if isinstance(_get(data, p), dict)]
            parent = draw(st.sampled_from([(), *mappings]))
            key = draw(st.sampled_from(known_keys) | st.text(max_size=8))
            _get(data, parent)[key] = draw(yaml_values)
        elif action == "replace":
            set_at(data, draw(st.sampled_from(paths)), draw(yaml_values))
        else:
            delete_at(data, draw(st.sampled_from(paths)))
    return data


def _check_parse(data: Any) -> None:
    outcome: SceneSpec | SceneFileError
    try:
        outcome = parse(data)
    except SceneFileError as error:
        outcome = error
    if isinstance(outcome, SceneFileError):
        assert outcome.path == str(PATH)
        assert str(outcome).startswith(f"{PATH}: ")
        assert outcome.message
    else:
        assert isinstance(outcome, SceneSpec)
        # What validated once validates again from its own dump, to the same spec.
        assert SceneSpec.model_validate(outcome.model_dump()) == outcome


@settings(max_examples=200, deadline=None)
@given(mutated_examples())
@hypothesis.example(example())  # the success branch runs at least once
def test_random_edits_of_the_example_give_a_spec_or_a_scene_file_error(data):
    _check_parse(data)


@settings(max_examples=100, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["camera", "lighting", "ground", "objects", "search"])
        | st.text(max_size=5),
        yaml_values,
        max_size=6,
    )
    | yaml_values
)
def test_random_documents_give_a_spec_or_a_scene_file_error(data):
    _check_parse(data)


# -- asset paths -------------------------------------------------------------------------------

INSIDE = "must stay inside the scene's folder"
ESCAPING_PATHS = [
    ("../duck.ply", INSIDE),
    ("meshes/../../duck.ply", INSIDE),
    ("meshes/../meshes/duck.ply", INSIDE),  # `..` is refused even when it comes back in
    ("/etc/passwd", "must be relative"),
    ("//server/share/duck.ply", "must be relative"),
    ("\\etc\\passwd", "must be relative"),
    ("C:duck.ply", "must be relative"),
    ("c:/meshes/duck.ply", "must be relative"),
    ("meshes\\duck.ply", INSIDE),
    ("meshes/missing.ply", "does not exist"),
    ("meshes", "does not exist"),  # a folder is not an asset file
    (".", "does not exist"),
    ("~/duck.ply", "does not exist"),  # no home expansion
]


@pytest.mark.parametrize(
    ("relative", "fragment"), ESCAPING_PATHS, ids=[p for p, _ in ESCAPING_PATHS]
)
@pytest.mark.parametrize(
    ("path", "field"),
    [
        (("objects", 3, "file"), "objects[3].file"),
        (("objects", 3, "texture"), "objects[3].texture"),
    ],
)
def test_bad_asset_paths_are_rejected(example_dir, relative, fragment, path, field):
    scene_path = write_scene(example_dir, set_at(example(), path, relative))
    with pytest.raises(SceneFileError) as info:
        load_scene(scene_path)
    assert info.value.field == field
    assert info.value.path == str(scene_path)
    assert fragment in info.value.message
    assert repr(relative) in info.value.message


def test_ground_texture_is_resolved_and_checked(example_dir):
    data = example()
    data["ground"] = {"size": 12.0, "texture": "textures/duck.png"}
    scene = load_scene(write_scene(example_dir, data))
    assert scene.assets["ground.texture"] == (example_dir / "textures" / "duck.png").resolve()
    data["ground"]["texture"] = "textures/tiles.png"  # not copied into the folder
    with pytest.raises(SceneFileError) as info:
        load_scene(write_scene(example_dir, data))
    assert info.value.field == "ground.texture"


def test_equivalent_spellings_inside_the_folder_are_accepted(example_dir):
    data = example()
    data["objects"][3]["file"] = "./meshes//duck.ply"
    scene = load_scene(write_scene(example_dir, data))
    assert scene.assets["objects[3].file"] == (example_dir / "meshes" / "duck.ply").resolve()


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A folder next to the scene folder, holding a file the scene must not reach."""
    folder = tmp_path / "outside"
    folder.mkdir()
    shutil.copyfile(SCENES / "meshes" / "duck.ply", folder / "secret.ply")
    return folder


@pytest.fixture
def scene_dir(tmp_path: Path) -> Path:
    folder = tmp_path / "scene"
    copy_example_assets(folder)
    return folder


def _symlink(link: Path, target: Path | str) -> None:
    try:
        link.symlink_to(target)
    except (OSError, NotImplementedError):
        pytest.skip("symlinks are not available here")


def test_symlink_to_a_file_outside_is_rejected(scene_dir, outside):
    _symlink(scene_dir / "meshes" / "link.ply", outside / "secret.ply")
    with pytest.raises(SceneFileError) as info:
        resolve_asset(scene_dir, "meshes/link.ply", "objects[3].file", scene_dir / "s.yaml")
    assert info.value.field == "objects[3].file"
    assert "leads outside the scene's folder" in info.value.message


def test_symlinked_folder_leading_outside_is_rejected(scene_dir, outside):
    _symlink(scene_dir / "shared", outside)
    data = set_at(example(), ("objects", 3, "file"), "shared/secret.ply")
    with pytest.raises(SceneFileError) as info:
        load_scene(write_scene(scene_dir, data))
    assert info.value.field == "objects[3].file"
    assert "leads outside" in info.value.message


def test_symlink_staying_inside_is_accepted(scene_dir):
    _symlink(scene_dir / "alias.ply", "meshes/duck.ply")
    resolved = resolve_asset(scene_dir, "alias.ply", "objects[3].file", scene_dir / "s.yaml")
    assert resolved == (scene_dir / "meshes" / "duck.ply").resolve()


def test_scene_folder_reached_through_a_symlink_still_works(scene_dir, tmp_path):
    _symlink(tmp_path / "via-link", scene_dir)
    scene = load_scene(write_scene(tmp_path / "via-link", example()))
    assert scene.assets["objects[3].file"] == (scene_dir / "meshes" / "duck.ply").resolve()


def test_symlink_loop_is_a_scene_file_error(scene_dir):
    _symlink(scene_dir / "loop-a", "loop-b")
    _symlink(scene_dir / "loop-b", "loop-a")
    data = set_at(example(), ("objects", 3, "file"), "loop-a")
    with pytest.raises(SceneFileError) as info:
        load_scene(write_scene(scene_dir, data))
    assert info.value.field == "objects[3].file"
    assert "'loop-a'" in info.value.message


@pytest.mark.parametrize(
    "relative",
    ["meshes/duck\x00.ply", "x" * 300 + ".ply", "meshes/" + "y" * 256],
    ids=["nul", "long-name", "long-name-in-folder"],
)
def test_unusable_asset_path_is_a_scene_file_error(scene_dir, relative):
    data = set_at(example(), ("objects", 3, "texture"), relative)
    with pytest.raises(SceneFileError) as info:
        load_scene(write_scene(scene_dir, data))
    assert info.value.field == "objects[3].texture"
    assert repr(relative) in info.value.message


# -- scene ids and unreadable files ------------------------------------------------------------


@pytest.mark.parametrize("stem", ["example", "Demo2", "my-scene_2.v1", "7", "a" * 128])
def test_scene_id_is_the_file_stem(example_dir, stem):
    path = write_scene(example_dir, example(), stem)
    assert load_scene(path).id == stem


@pytest.mark.parametrize(
    "stem", [".hidden", "-dash", "_under", "two words", "caf\u00e9", "a" * 129]
)
def test_bad_file_stem_is_rejected(example_dir, stem):
    path = write_scene(example_dir, example(), stem)
    with pytest.raises(SceneFileError) as info:
        load_scene(path)
    assert info.value.field is None
    assert f"scene id {stem!r} (the file stem) is not allowed" in info.value.message


def test_unreadable_scene_files_are_scene_file_errors(tmp_path):
    folder = tmp_path / "folder.yaml"
    folder.mkdir()
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"camera: \xff\xfe\n")
    for path in (folder, binary, tmp_path / "missing.yaml"):
        with pytest.raises(SceneFileError) as info:
            load_scene(path)
        assert "cannot read the file" in info.value.message


# -- JSON Schema -------------------------------------------------------------------------------


def _schema_errors(schema: dict[str, Any]) -> Callable[[Any], list[str]]:
    """Error messages of a Draft 2020-12 validator for ``schema`` (jsonschema, or jsonschema_rs,
    which schemathesis brings along)."""
    try:
        import jsonschema
    except ImportError:
        jsonschema_rs = pytest.importorskip("jsonschema_rs")
        assert jsonschema_rs.meta.is_valid(schema)
        rs_validator = jsonschema_rs.Draft202012Validator(schema)
        return lambda instance: [e.message for e in rs_validator.iter_errors(instance)]
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    return lambda instance: [e.message for e in validator.iter_errors(instance)]


@pytest.fixture(scope="module")
def schema_errors() -> Callable[[Any], list[str]]:
    return _schema_errors(json.loads(SCHEMA_PATH.read_text(encoding="utf-8")))


def test_committed_schema_is_up_to_date(capsys):
    assert SCHEMA_PATH == ROOT / "docs" / "scene.schema.json"
    assert SCHEMA_PATH.read_text(encoding="utf-8") == render_schema(), (
        "docs/scene.schema.json is stale: run python -m tools.export_schema"
    )
    assert main(["--check"]) == 0
    assert "up to date" in capsys.readouterr().out


def test_schema_names_the_format():
    schema = scene_json_schema()
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["title"] == "COSMOS 3D Search scene"
    assert set(schema["required"]) == {"camera", "lighting", "ground", "objects"}


def test_export_schema_writes_pretty_sorted_json_and_checks_it(tmp_path, capsys):
    out = tmp_path / "docs" / "scene.schema.json"
    assert main(["--check", "--out", str(out)]) == 1  # missing
    assert not out.exists()
    assert main(["--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    assert text.endswith("}\n")
    assert json.loads(text) == scene_json_schema()
    assert text == json.dumps(json.loads(text), indent=2, sort_keys=True, ensure_ascii=False) + "\n"
    assert main(["--check", "--out", str(out)]) == 0
    out.write_text(text.replace('"CameraSpec"', '"Kamera"'), encoding="utf-8")
    assert main(["--check", "--out", str(out)]) == 1
    assert "out of date" in capsys.readouterr().err
    out.write_text(text.rstrip("\n"), encoding="utf-8")  # the trailing newline counts too
    assert main(["--check", "--out", str(out)]) == 1


@pytest.mark.parametrize("scene_id", BUILTIN)
def test_builtin_scenes_validate_against_the_json_schema(schema_errors, scene_id):
    data = yaml.safe_load((SCENES / f"{scene_id}.yaml").read_text(encoding="utf-8"))
    assert schema_errors(data) == []


def test_readme_example_and_dumped_specs_validate_against_the_json_schema(schema_errors):
    assert schema_errors(example()) == []
    spec = parse(example())
    assert schema_errors(spec.model_dump(mode="json")) == []
    for scene_id in BUILTIN:
        dumped = load_scene(SCENES / f"{scene_id}.yaml").spec.model_dump(mode="json")
        assert schema_errors(dumped) == []


SCHEMA_REJECTS: list[tuple[tuple[str | int, ...], Any]] = [
    (("extra",), 1),
    (("objects", 0, "colour"), [1, 0, 0]),
    (("objects", 0, "size"), 1.0),  # a cube's key on a sphere
    (("objects", 0, "shape"), "torus"),
    (("ground", "color"), [0.5, 0.5]),
    (("objects", 1, "position"), [0, 0, 0]),
    (("objects", 1, "color", 0), 1.5),
    (("camera",), DELETE),
    (("camera", "fov_deg"), 170),
    (("camera", "width"), 320.5),
    (("objects",), []),
    (("objects", 0, "name"), "a b"),
]


@pytest.mark.parametrize(
    ("path", "value"),
    SCHEMA_REJECTS,
    ids=[".".join(map(str, p)) + ("-deleted" if v is DELETE else "") for p, v in SCHEMA_REJECTS],
)
def test_json_schema_rejects_what_the_models_reject(schema_errors, path, value):
    data = edit(example(), path, value)
    with pytest.raises(SceneFileError):
        parse(data)
    assert schema_errors(data) != []


def test_schema_file_has_unix_newlines_and_one_trailing_newline():
    raw = SCHEMA_PATH.read_bytes()
    assert b"\r" not in raw
    assert raw.endswith(b"}\n")


def test_a_key_given_twice_is_an_error_not_last_wins(tmp_path):
    text = "camera: {fov_deg: 45, width: 320, height: 240, radius: 8.0}\ncamera: {}\n"
    with pytest.raises(SceneFileError) as caught:
        parse_scene(text, tmp_path / "twice.yaml")
    assert caught.value.field == "line 2, column 1"
    assert "duplicate key 'camera'" in caught.value.message
