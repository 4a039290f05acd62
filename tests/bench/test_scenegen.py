"""The bench's random scenes (cosmos/bench/scenes.py): seeded, valid, varied, renderable."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosmos.bench.scenes import MESH_KINDS, footprint, generate_scene, make_mesh, mesh_extent
from scene_assets import read_ply
from services.common.geometry.pose import Pose
from services.common.geometry.scene import MeshObject, load_scene
from services.common.scene_models import model_dir, object_classes

SEEDS = range(40)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scenes")
    return [load_scene(generate_scene(seed, folder, f"s{seed}")) for seed in SEEDS]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_the_same_seed_writes_the_same_files(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    generate_scene(np.random.default_rng([7, 1]), a, "x")
    generate_scene(np.random.default_rng([7, 1]), b, "x")
    assert _files(a) == _files(b)
    generate_scene(np.random.default_rng([7, 2]), b, "x")
    assert _files(a) != _files(b)


def test_a_stale_model_of_the_id_is_removed(tmp_path):
    stale = model_dir(tmp_path / "x.yaml")
    stale.mkdir(parents=True)
    (stale / "model.onnx").write_bytes(b"old")
    generate_scene(3, tmp_path, "x")
    assert not stale.exists()


def test_scenes_are_within_the_promised_ranges(scenes):
    for scene in scenes:
        spec = scene.spec
        assert 3 <= len(spec.objects) <= 10
        assert 35 <= spec.camera.fov_deg <= 60
        assert 256 <= spec.camera.width <= 480
        assert 1.2 <= spec.camera.width / spec.camera.height <= 1.61
        assert 6 <= spec.camera.radius
        step = spec.search.angle_step_deg
        assert 5 <= step <= 10
        assert spec.search.min_theta_deg == step
        assert 72 <= spec.search.max_theta_deg <= 82


def test_objects_stand_on_the_ground_apart_and_the_camera_clears_them(scenes):
    for scene in scenes:
        spec = scene.spec
        half = spec.ground.size / 2
        discs = [(*o.position, *footprint(o, scene.directory)) for o in spec.objects]
        for i, (x, y, reach, height) in enumerate(discs):
            assert max(abs(x), abs(y)) + reach <= half, (scene.id, i)
            assert height > 0
            reach_from_centre = math.hypot(math.hypot(x, y) + reach, height)
            assert spec.camera.radius >= 1.5 * reach_from_centre - 1e-3, scene.id
            for ox, oy, oreach, _ in discs[i + 1 :]:
                assert math.hypot(x - ox, y - oy) >= reach + oreach, scene.id


def test_meshes_are_new_shapes_readable_as_ply(scenes):
    meshes = [(s, o) for s in scenes for o in s.spec.objects if isinstance(o, MeshObject)]
    assert meshes
    for scene, obj in meshes:
        assert "duck" not in obj.file
        assert "arch" not in obj.file
        mesh = read_ply(scene.directory / obj.file)
        assert mesh.faces.shape[1] == 3
        assert mesh.faces.max() < len(mesh.vertices)
        assert mesh_extent(scene.directory / obj.file).height > 0


@pytest.mark.parametrize("kind", MESH_KINDS)
def test_closed_meshes_have_outward_faces(kind):
    """Every mesh encloses a positive volume (divergence theorem over its triangles)."""
    vertices, faces = make_mesh(kind, np.random.default_rng(5))
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
    assert volume > 0.05


def test_scenes_vary_across_seeds(scenes):
    kinds = {
        Path(o.file).stem.split("-")[-1] if isinstance(o, MeshObject) else o.shape
        for s in scenes
        for o in s.spec.objects
    }
    assert kinds >= {"sphere", "cube", "cylinder", "cone", *MESH_KINDS}
    assert any(s.spec.ground.texture for s in scenes)
    assert any(s.spec.ground.color for s in scenes)
    assert any(o.texture for s in scenes for o in s.spec.objects)
    assert len({s.spec.camera.width / s.spec.camera.height for s in scenes}) >= 3
    assert len({s.spec.search.angle_step_deg for s in scenes}) >= 5
    twins = [s for s in scenes if any(len(c.objects) > 1 for c in object_classes(s.spec))]
    assert twins, "no scene has two identical objects"

    def near(scene):
        colours = [np.asarray(o.color) for o in scene.spec.objects if o.color is not None]
        return any(
            0.03 < np.linalg.norm(p - q) <= 0.1
            for i, p in enumerate(colours)
            for q in colours[i + 1 :]
        )

    assert any(near(s) for s in scenes), "no scene has near colours"


def test_a_generated_scene_renders_with_its_objects_in_view(tmp_path):
    from services.renderer.engine import RenderEngine

    scene = load_scene(generate_scene(11, tmp_path, "r"))
    engine = RenderEngine("auto", cache_size=1)
    engine.start()
    try:
        pose = Pose(theta_deg=40.0, phi_deg=30.0)
        image = engine.render(scene, pose, 160, 120, 4, 0).rgb
        truth = engine.annotate(scene, pose, 160, 120, None)
    finally:
        engine.close()
    assert image.shape == (120, 160, 3)
    assert image.std() > 5
    assert sum(o.visible_pixels > 0 for o in truth.objects) >= 2
