"""Onboarding end to end through the real services: a CI-sized onboarding (a tiny dataset, one
epoch) of a generated scene the project never trained on, then a search on it through the real
renderer, detector, optimizer and controller processes, which must use that scene's own model."""

from __future__ import annotations

import json

import pytest

from cosmos.bench.runner import local_stack
from cosmos.bench.scenes import generate_scene
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import PoseQuery
from services.common.geometry.scene import load_scene
from services.common.scene_models import SIDECAR_NAME, model_dir, object_classes
from services.controller.client import ControllerClient
from services.detector.client import DetectorClient
from services.renderer.client import RendererClient

pytest.importorskip("torch")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_an_onboarded_scene_is_searched_with_its_own_model(tmp_path):
    from training.onboard import OnboardOptions, onboard_scene

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    path = generate_scene(11, scenes, "yard")
    labels = [c.label for c in object_classes(load_scene(path).spec)]
    with local_stack(tmp_path / "stack", scene_dirs=(scenes,)) as stack:
        # Onboarded while the stack runs: the detector must pick the model up by itself.
        report = onboard_scene(path, OnboardOptions.tiny(), work_dir=tmp_path / "work")
        sidecar = json.loads((model_dir(path) / SIDECAR_NAME).read_text())
        assert list(report.classes) == labels == sidecar["classes"]

        with DetectorClient(stack.detectors[0], token=stack.service_token) as detector:
            models = {s.scene: s for s in detector.models().scenes}
            assert models["yard"].state == "serving"
            assert models["yard"].model is not None
            assert list(models["yard"].model.classes) == labels

        with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
            target = renderer.render_png(
                RenderRequest(scene="yard", pose=PoseQuery(lat=2, lon=3), spp=16, seed=5)
            )
        with ControllerClient(stack.controller, api_key=stack.api_key) as client:
            search = client.submit(target, "yard", seed=3, max_iterations=4)
            *_, final = client.follow(search.id, timeout_s=120)

    assert final.status in {"succeeded", "failed"}, final
    assert final.target_model is not None, final.error
    assert final.target_model.scene == "yard"
    assert final.target_model.sha256 == sidecar["sha256"]
    assert final.target_detections, "the tiny model found nothing in the target"
    assert {d.label for d in final.target_detections} <= set(labels)
    assert final.iterations
    for iteration in final.iterations:
        assert iteration.detector_sha256 == sidecar["sha256"]
        assert {d.label for d in iteration.detections} <= set(labels)
