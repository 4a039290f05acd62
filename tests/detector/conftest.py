"""The detector's fixtures: a real detector process serving a synthetic model and a scene's own."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from services.detector.synthetic import constant_model
from tests.scene_model_support import add_scene, onboard
from tests.support import ServiceProcess, running_service

APP = "services.detector.app:app"
UPLOAD_LIMIT = 200_000


def one_sphere_model(directory: Path) -> Path:
    """A synthetic general model (classes sphere, cube) that always sees one sphere at network
    input (80, 80)-(120, 160) with confidence 0.9."""
    return constant_model(
        directory / "constant.onnx",
        np.array([[100], [120], [40], [80], [0.9], [0.0]], np.float32),
        classes=["sphere", "cube"],
    )


@pytest.fixture(scope="module")
def detector_process(tmp_path_factory) -> Iterator[ServiceProcess]:
    """A real detector serving a synthetic model: one sphere at input (80, 80)-(120, 160); and
    scene ``field`` (the demo) with its own model."""
    directory = tmp_path_factory.mktemp("detector-http")
    scenes = directory / "scenes"
    scenes.mkdir()
    add_scene(scenes, "field")
    onboard(scenes, "field")
    model = one_sphere_model(directory)
    env = {
        "COSMOS_DETECTOR_MODEL": str(model),
        "COSMOS_DETECTOR_THREADS": "1",
        "COSMOS_DETECTOR_MAX_UPLOAD_BYTES": str(UPLOAD_LIMIT),
        "COSMOS_DETECTOR_MAX_IMAGE_PIXELS": "1000000",
        "COSMOS_SCENES_DIR": str(scenes),
    }
    with running_service(APP, directory / "logs", env) as service:
        yield service
