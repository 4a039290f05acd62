"""Free poses on a generated scene served by the general detector (issue 23: "with the general
model, assignments are enumerated inside RANSAC"): a target of ``cosmos bench --free``'s random
scenes rendered by the real engine, detected by the real general ONNX model, solved from its
boxes alone.

The general model names shapes, and on a generated scene's meshes it names the wrong ones (a
star prism a cube, a tower a cylinder). When a label had to equal the object's shape, this
target's detections paired one object, and the answer was ``ambiguous: only 1 object(s)
paired``; measured after the fix: 5 pairs, 1.5 % of the radius and 1.2°."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.geometry.free_camera import FreeCamera
from services.detector.detect import DetectOptions, detections_from_output
from services.detector.letterbox import letterbox
from services.detector.model import DetectorModel
from services.detector.settings import DetectorSettings
from services.optimizer.free import Intrinsics, scene_objects, solve_free_pose
from services.optimizer.free.hypotheses import compatibility

SEED, SCENE = 3, 1
"""Scene rand3-1 of ``cosmos bench --free --random-scenes 2 --seed 3``: nine meshes."""
CAMERA = FreeCamera(
    position=(-4.9106168222926385, 3.587977782430425, 1.2453178115698222),
    yaw_deg=320.84214857843835,
    pitch_deg=16.766284204346324,
    roll_deg=0.8370091310681822,
    fov_deg=38.04545921280707,
)
"""The first target that scene's bench run with ``--n 6`` drew before its elevations were
stratified, on the scene's 304 x 190 film."""
FILM = (304, 190)


@pytest.fixture(scope="module")
def general_target(engine, tmp_path_factory):
    folder = tmp_path_factory.mktemp("scenes")
    scene_id = f"rand{SEED}-{SCENE}"
    generate_scene(np.random.default_rng([SEED, SCENE]), folder, scene_id)
    catalog = SceneCatalog([folder])
    scene = catalog.get(scene_id)
    request = RenderRequest(
        scene=scene_id, camera=CAMERA, width=FILM[0], height=FILM[1], spp=16, seed=0
    )
    with LocalRenderer(catalog, engine=engine) as renderer:
        png, annotations = renderer.render_png(request), renderer.annotations(request)
    settings = DetectorSettings()
    model = DetectorModel(settings.detector_model, threads=1)
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    tensor, box = letterbox(rgb, model.layout.input_size)
    output = model.run(tensor[np.newaxis])[0]
    options = DetectOptions.from_settings(settings)
    detections = detections_from_output(output, box, model.classes, rgb, options)
    return scene_objects(scene.spec, scene.assets), annotations, detections, rgb.shape[1::-1]


def test_general_model_labels_pair_the_visible_objects(general_target):
    objects, annotations, detections, (width, height) = general_target
    # the cause: most labels name no object's shape, so fewer than three detections had an
    # object to pair with when a label had to be the object's shape
    fits = compatibility(objects, tuple(d.label for d in detections))
    assert int(fits.any(axis=1).sum()) < 3 <= len(detections)
    truth = annotations.camera
    k = Intrinsics(truth.fx, truth.fy, truth.cx, truth.cy)
    answer = solve_free_pose(objects, detections, width, height, k)
    assert answer.status == "found", answer.reason
    assert answer.pose.inliers >= 3
    moved = float(np.linalg.norm(np.asarray(answer.pose.position) - truth.position))
    relative = answer.pose.rotation() @ np.asarray(truth.rotation)
    turned = math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
    assert moved < 0.05 * objects.radius
    assert turned < 2.0
    # every pair is the object the detection's box shows (the renderer's own boxes)
    shown = {o.name: np.asarray(o.box) for o in annotations.objects if o.box is not None}
    for pair in answer.pose.correspondences:
        box = np.asarray(detections[pair.detection].box)
        assert np.sqrt(np.mean((box - shown[pair.object]) ** 2)) < 6.0


def test_too_few_general_detections_point_to_a_detector_of_the_scene(general_target):
    """Two boxes give no pose. With the general model, the likelier cause is its missing the
    scene's unfamiliar shapes, not the photo: the advice names onboarding; the same two boxes
    named by a scene's own detector (the objects' names) do not."""
    objects, annotations, detections, (width, height) = general_target
    truth = annotations.camera
    k = Intrinsics(truth.fx, truth.fy, truth.cx, truth.cy)
    two = sorted(detections, key=lambda d: -d.confidence)[:2]
    answer = solve_free_pose(objects, two, width, height, k)
    assert answer.status == "ambiguous", answer.reason
    assert "cosmos scenes add" in answer.reason
    shown = {o.name: np.asarray(o.box) for o in annotations.objects if o.box is not None}

    def named(d):
        box = np.asarray(d.box)
        name = min(shown, key=lambda n: float(np.abs(shown[n] - box).max()))
        return d.model_copy(update={"label": name})

    own = solve_free_pose(objects, [named(d) for d in two], width, height, k)
    assert own.status == "ambiguous", own.reason
    assert "only 2 object(s) paired" in own.reason
    assert "cosmos scenes add" not in own.reason
