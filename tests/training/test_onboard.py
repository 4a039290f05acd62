"""Onboarding a scene: its dataset, the warm start, the installed model and the CLI."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from cosmos.cli import main
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.geometry.scene import SceneFileError, load_scene
from services.common.scene_models import (
    MODEL_CARD_NAME,
    MODEL_FILE_NAME,
    SIDECAR_NAME,
    model_dir,
    object_classes,
)
from training.onboard import OnboardOptions, TorchMissingError, onboard_scene

SCENE = """\
camera: {fov_deg: 50, width: 160, height: 128, radius: 6.0}
lighting:
  point: {position: [2.0, -3.0, 7.0], intensity: 150.0}
  ambient: 0.15
ground: {size: 10.0, texture: textures/wood.png}
objects:
  - {name: ball, shape: sphere, position: [1.0, 0.5], radius: 0.5, color: [0.2, 0.6, 0.9]}
  - {name: box1, shape: cube, position: [-1.0, -0.8], size: 0.7, color: [0.9, 0.9, 0.2]}
  - {name: box2, shape: cube, position: [-1.2, 1.2], size: 0.7, yaw_deg: 30, color: [0.9, 0.9, 0.2]}
search: {angle_step_deg: 15, min_theta_deg: 15, max_theta_deg: 75}
"""


def _scene_folder(root: Path, text: str = SCENE) -> Path:
    (root / "textures").mkdir(parents=True, exist_ok=True)
    shutil.copy(BUILTIN_SCENES_DIR / "textures" / "wood.png", root / "textures" / "wood.png")
    path = root / "mini.yaml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def onboarded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny onboarding of a 3-object scene (run once for the module): scene file, work dir."""
    pytest.importorskip("torch")
    root = tmp_path_factory.mktemp("scene")
    path = _scene_folder(root)
    work = root / "work"
    onboard_scene(path, OnboardOptions.tiny(), work_dir=work)
    return path, work


@pytest.mark.slow
def test_tiny_onboarding_installs_a_model_of_the_scene_classes(onboarded):
    path, _ = onboarded
    folder = model_dir(path)
    sidecar = json.loads((folder / SIDECAR_NAME).read_text())
    labels = [c.label for c in object_classes(load_scene(path).spec)]
    assert labels == ["ball", "box1+box2"]  # the two cubes look alike: one class
    assert sidecar["classes"] == labels
    assert sidecar["scene"] == "mini"
    data = (folder / MODEL_FILE_NAME).read_bytes()
    assert sidecar["sha256"] == hashlib.sha256(data).hexdigest()
    card = (folder / MODEL_CARD_NAME).read_text()
    assert "box1+box2" in card
    assert "cosmos scenes add" in card
    assert sorted(p.name for p in folder.iterdir()) == [MODEL_CARD_NAME, SIDECAR_NAME, "model.onnx"]


@pytest.mark.slow
def test_a_failed_export_leaves_the_installed_model_alone(onboarded, monkeypatch):
    path, work = onboarded
    folder = model_dir(path)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    import training.export

    def broken(*args, **kwargs):
        raise RuntimeError("export failed")

    monkeypatch.setattr(training.export, "onnx_model", broken)
    with pytest.raises(RuntimeError, match="export failed"):
        onboard_scene(path, OnboardOptions.tiny(), work_dir=work)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


@pytest.mark.slow
def test_cli_scenes_add_resumes_and_prints_the_model_path(onboarded, capsys, monkeypatch):
    path, work = onboarded
    import training.scene_dataset as scene_dataset

    def no_render(*args, **kwargs):
        raise AssertionError("rendered a finished sample again")

    monkeypatch.setattr(scene_dataset.RenderEngine, "render", no_render)
    assert main(["scenes", "add", str(path), "--tiny", "--work", str(work)]) == 0
    out = capsys.readouterr().out
    assert "1 epochs" in out
    assert str(model_dir(path) / MODEL_FILE_NAME) in out
    assert "precision" in out
    assert f"COSMOS_SCENES_DIR={path.parent}" in out


def test_scene_views_depend_only_on_seed_and_index(tmp_path):
    from services.common.geometry.free_camera import FreeCamera
    from training.drone_views import DRONE_FOV_SPREAD, DRONE_ROLL_DEG
    from training.scene_dataset import scene_views

    scene = load_scene(_scene_folder(tmp_path))
    all_views = {v.index: (v.pose, v.spp, v.seed, v.scene.spec) for v in scene_views(scene, 3, 10)}
    odd = {
        v.index: (v.pose, v.spp, v.seed, v.scene.spec)
        for v in scene_views(scene, 3, 10, skip=lambda i: i % 2 == 0)
    }
    assert odd == {i: all_views[i] for i in range(1, 10, 2)}
    other = [v.pose for v in scene_views(scene, 4, 10)]
    assert other != [all_views[i][0] for i in range(10)]
    search = scene.spec.search
    for index, (pose, _, _, spec) in all_views.items():
        if index % 3 == 2:  # a drone view
            assert isinstance(pose, FreeCamera)
            assert pose.position[2] > 0.0
            assert 10.0 <= pose.pitch_deg <= 90.0
            assert abs(pose.roll_deg) <= DRONE_ROLL_DEG
            fov = scene.spec.camera.fov_deg
            assert (1 - DRONE_FOV_SPREAD) * fov <= pose.fov_deg <= (1 + DRONE_FOV_SPREAD) * fov
        else:
            assert search.min_theta_deg - 1e-9 <= pose.theta_deg <= search.max_theta_deg + 1e-9
        assert spec.objects == scene.spec.objects
        assert 0.5 * 150 <= spec.lighting.point.intensity <= 2 * 150


def test_drone_views_look_at_the_objects_from_any_height(tmp_path):
    """Seeded drone cameras: every one sees the objects' area in front of it, a quarter look
    straight down, and their distances span the range."""
    from training.drone_views import DRONE_DISTANCE, drone_camera

    scene = load_scene(_scene_folder(tmp_path))
    rng = np.random.default_rng(5)
    cameras = [drone_camera(scene, rng) for _ in range(200)]
    r = scene.spec.camera.radius
    nadir = sum(c.pitch_deg == 90.0 for c in cameras)
    assert 30 <= nadir <= 70
    heights = [c.position[2] / r for c in cameras]
    assert min(heights) < 0.6 * DRONE_DISTANCE[1]
    assert max(heights) > 0.8 * DRONE_DISTANCE[1]
    centre = np.mean([o.position for o in scene.spec.objects], axis=0)
    for c in cameras:
        forward = c.rotation()[:, 2]  # the camera's +z in the world: where it looks
        to_objects = np.array([*centre, 0.0]) - np.asarray(c.position)
        assert forward @ to_objects > 0.0


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda s: s.replace("radius: 0.5,", "radius: -1,"), "objects[0].radius"),
        (
            lambda s: s.replace(
                "- {name: ball",
                "- {name: m, shape: mesh, file: meshes/no.ply, position: [0, 0]}\n  - {name: ball",
            ),
            "objects[0].file",
        ),
        (lambda s: s.replace("textures/wood.png", "../wood.png"), "ground.texture"),
    ],
)
def test_an_unusable_scene_fails_with_its_field_before_anything_is_written(tmp_path, edit, field):
    path = _scene_folder(tmp_path / "s", edit(SCENE))
    with pytest.raises(SceneFileError) as info:
        onboard_scene(path, OnboardOptions.tiny(), work_dir=tmp_path / "work")
    assert info.value.field == field
    assert not model_dir(path).exists()
    assert not (tmp_path / "work").exists()


def test_cli_reports_an_invalid_scene_with_exit_status_2(tmp_path, capsys):
    path = _scene_folder(tmp_path, SCENE.replace("size: 0.7,", "size: zero,", 1))
    assert main(["onboard", str(path), "--work", str(tmp_path / "w")]) == 2
    assert "objects[1].size" in capsys.readouterr().err


def test_without_torch_onboarding_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(TorchMissingError, match=r"pip install -e \".\[train\]\""):
        onboard_scene(_scene_folder(tmp_path), work_dir=tmp_path / "work")


def test_the_warm_start_reproduces_the_general_model():
    torch = pytest.importorskip("torch")
    import onnxruntime as ort

    from training.model import ExportWrapper
    from training.onboard import GENERAL_MODEL
    from training.warm_start import warm_start

    shapes = ["cube", "sphere", "cube"]
    model = warm_start(GENERAL_MODEL, shapes)
    x = torch.rand(2, 3, 256, 320)
    with torch.no_grad():
        ours = ExportWrapper(model, 256, 320).eval()(x).numpy()
    session = ort.InferenceSession(str(GENERAL_MODEL), providers=["CPUExecutionProvider"])
    general = session.run(None, {"images": x.numpy()})[0]
    np.testing.assert_allclose(ours[:, :4], general[:, :4], atol=1e-3)  # boxes, input px
    # Each scene class starts as its shape's class of the general model (cube = 1, sphere = 0).
    np.testing.assert_allclose(ours[:, 4:], general[:, [4 + 1, 4 + 0, 4 + 1]], atol=1e-4)


def test_training_uses_only_the_idle_cores(monkeypatch):
    from training.onboard import idle_cores

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    monkeypatch.setattr("os.getloadavg", lambda: (5.0, 5.0, 5.0))
    assert idle_cores() == 1
    monkeypatch.setattr("os.getloadavg", lambda: (0.1, 0.1, 0.1))
    assert idle_cores() == 2
