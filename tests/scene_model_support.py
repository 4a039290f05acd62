"""Test support for scene models: a scene copied from the demo and a model installed for it as
onboarding installs one (the sidecar first, then the ONNX file renamed into place).

The model is a copy of the shipped general model (five output classes) with a sidecar naming the
demo's five balls, so it finds the same spheres labelled with the balls' names.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.scene_models import MODEL_FILE_NAME, SIDECAR_NAME
from services.detector.settings import DEFAULT_MODEL
from services.detector.synthetic import constant_model

__all__ = ["BALLS", "GENERAL_SIDECAR", "add_scene", "balls_png", "blue_model", "onboard", "sha256"]

BALLS = ["red", "green", "blue", "yellow", "magenta"]  # the demo's objects, in order
GENERAL_SIDECAR = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def add_scene(scenes: Path, scene_id: str, source: Path = BUILTIN_SCENES_DIR / "demo.yaml") -> Path:
    """``scenes/<scene_id>.yaml``, a copy of ``source`` (the demo's assets are all built in)."""
    path = scenes / f"{scene_id}.yaml"
    shutil.copyfile(source, path)
    return path


def onboard(
    scenes: Path,
    scene_id: str,
    onnx: Path = DEFAULT_MODEL,
    *,
    classes: list[str] | None = None,
    scene: str | None = None,
    sha: str | None = None,
    install: bool = True,
) -> Path:
    """Write ``scene_id``'s model as onboarding does: the sidecar (classes, scene, sha256 of
    ``onnx``, unless given), then ``onnx`` renamed into place (unless ``install`` is False: a
    model half written). Returns the model's folder."""
    folder = scenes / f"{scene_id}.detector"
    folder.mkdir(exist_ok=True)
    sidecar = {
        **GENERAL_SIDECAR,
        "name": f"{scene_id}-detector",
        "classes": BALLS if classes is None else classes,
        "scene": scene_id if scene is None else scene,
        "sha256": sha or sha256(onnx),
    }
    (folder / SIDECAR_NAME).write_text(json.dumps(sidecar))
    if install:
        staged = folder / "model.onnx.part"
        shutil.copyfile(onnx, staged)
        os.replace(staged, folder / MODEL_FILE_NAME)
    return folder


def stand_in_onboarding(scene_path: Path, work_dir: Path) -> None:
    """Onboarding stood in for (``training.onboard.onboard_scene``'s shape): a model that finds
    one object of the scene's first class everywhere, installed beside the scene file as
    onboarding installs one."""
    from services.common.geometry.scene import load_scene
    from services.common.scene_models import object_classes

    work_dir.mkdir(parents=True)
    classes = [c.label for c in object_classes(load_scene(scene_path).spec)]
    predictions = np.zeros((4 + len(classes), 1), np.float32)
    predictions[:4, 0] = (160, 128, 60, 60)
    predictions[4, 0] = 0.9
    model = constant_model(work_dir / "m.onnx", predictions, input_size=(320, 256))
    onboard(scene_path.parent, scene_path.stem, model, classes=classes)


def blue_model(directory: Path) -> Path:
    """A five-class model that always finds one ball of class 2 (blue), at a 320x256 input's
    (100, 80)-(140, 120)."""
    predictions = np.zeros((4 + 5, 1), np.float32)
    predictions[:4, 0] = (120, 100, 40, 40)
    predictions[4 + 2, 0] = 0.9
    return constant_model(directory / "blue.onnx", predictions, input_size=(320, 256))


def balls_png() -> bytes:
    """Two shaded balls, red and blue, on a grey floor: the general model finds two spheres."""
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    image = np.empty((h, w, 3), np.float32)
    image[:] = np.array([0.55, 0.55, 0.5]) * (0.7 + 0.3 * yy[..., None] / h)
    for cx, cy, r, colour in [(100, 130, 35, (0.85, 0.08, 0.08)), (220, 110, 30, (0.1, 0.2, 0.85))]:
        d2 = (xx - cx) ** 2 + (yy - cy) ** 2
        z = np.sqrt(np.clip(r * r - d2, 0, None)) / r
        shade = np.clip(
            0.25 + 0.75 * (-0.4 * (xx - cx) / r - 0.5 * (yy - cy) / r + 0.77 * z), 0.1, 1
        )
        inside = d2 < r * r
        image[inside] = (np.array(colour) * shade[..., None])[inside]
    rgb = (np.clip(image, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return buffer.tobytes()
