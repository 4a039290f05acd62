"""``POST /free-pose`` in process (ASGI transport, lifespan run) on the built-in scenes' real
objects: boxes annotated by the real renderer at free cameras, the answer's fields, the scene
objects' cache, and problem+json for bad input."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator
from dataclasses import replace

import httpx
import numpy as np
import pytest

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.optimizer.app import create_app
from services.optimizer.free import scene_objects, solve_free_pose
from services.optimizer.free_pose import _renderable
from services.optimizer.settings import OptimizerSettings
from services.renderer.view import resolve_free_camera
from tests.support import in_process

pytestmark = pytest.mark.anyio

W, H = 320, 240
TILTED = FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0)


@pytest.fixture(scope="module")
async def app_and_client() -> AsyncIterator[tuple[object, httpx.AsyncClient]]:
    settings = OptimizerSettings()
    app = create_app(settings)
    async with in_process(app, "http://optimizer", settings.token()) as client:
        yield app, client


@pytest.fixture
def client(app_and_client) -> httpx.AsyncClient:
    return app_and_client[1]


def target(engine, catalog, scene_id: str, camera: FreeCamera) -> tuple[dict, object]:
    """The visible boxes of the scene's objects seen from ``camera``, labelled as the scene's own
    detector labels them, and the true pinhole camera."""
    scene = catalog.get(scene_id)
    view = resolve_free_camera(scene, camera, W, H)
    annotations = engine.annotate(scene, view, W, H, None)
    labels = scene_objects(scene.spec, scene.assets).labels
    detections = [
        {"label": labels[i], "class_id": i, "confidence": 0.9, "box": list(obj.box)}
        for i, obj in enumerate(annotations.objects)
        if obj.box is not None and obj.visible_fraction >= 0.6
    ]
    return {"image_size": [W, H], "detections": detections}, annotations.camera


def pose_error(pose: dict, truth) -> tuple[float, float]:
    moved = math.dist(pose["position"], truth.position)
    camera = FreeCamera(position=pose["position"], quaternion_wxyz=pose["quaternion_wxyz"])
    relative = camera.rotation().T @ np.asarray(truth.rotation).T
    turned = math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
    return moved, turned


async def test_given_intrinsics_give_the_camera_and_its_nearest_grid_pose(client, engine, catalog):
    image, truth = target(engine, catalog, "garden", TILTED)
    intrinsics = {"fx_px": truth.fx, "fy_px": truth.fy, "cx_px": truth.cx, "cy_px": truth.cy}
    answer = await client.post(
        "/free-pose", json={"scene": "garden", "target": image, "intrinsics": intrinsics}
    )
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["status"] == "found", body["reason"]
    pose = body["pose"]
    moved, turned = pose_error(pose, truth)
    assert moved < 0.02 * 8.0
    assert turned < 1.0
    assert pose["intrinsics"]["source"] == "given"
    assert pose["intrinsics"]["fx_px"] == pytest.approx(truth.fx)
    assert 0.5 < pose["confidence"] <= 1.0
    assert pose["position_sigma"] > 0
    assert pose["rotation_sigma_deg"] > 0
    pairs = pose["correspondences"]
    assert len(pairs) == len(image["detections"])
    for pair in pairs:  # the predicted box (unclipped) is where the detection is
        box = image["detections"][pair["detection"]]["box"]
        predicted = np.clip(pair["predicted_box"], 0, [W, H, W, H])
        assert np.allclose(predicted, box, atol=3.0)
    # yaw/pitch/roll are the quaternion's: the look-at camera's roll of 20°
    assert pose["yaw_pitch_roll_deg"][2] == pytest.approx(20.0, abs=1.5)
    # the camera stands at θ = acos(4 / |(-6, 2, 4)|) ≈ 58°, φ ≈ 162°
    grid = body["nearest_grid"]
    assert abs(grid["theta_deg"] - 57.7) <= 7.5 / 2 + 0.5
    assert abs(grid["phi_deg"] - 161.6) <= 7.5


async def test_intrinsics_from_the_exif_are_used_as_given_and_said_to_be(client, engine, catalog):
    image, truth = target(engine, catalog, "garden", TILTED)
    k = {"fx_px": truth.fx, "fy_px": truth.fy}
    answers = [
        (
            await client.post(
                "/free-pose",
                json={"scene": "garden", "target": image, "intrinsics": {**k, "source": source}},
            )
        ).json()
        for source in ("given", "exif")
    ]
    given, exif = answers
    assert exif["pose"]["intrinsics"]["source"] == "exif"
    assert "EXIF" in exif["reason"]
    assert exif["pose"]["position"] == given["pose"]["position"]
    assert exif["pose"]["intrinsics"]["fx_px"] == pytest.approx(truth.fx)
    assert exif["status"] == given["status"]


async def test_without_intrinsics_the_focal_length_is_estimated(client, engine, catalog):
    image, truth = target(engine, catalog, "garden", TILTED)
    body = (await client.post("/free-pose", json={"scene": "garden", "target": image})).json()
    assert body["pose"]["intrinsics"]["source"] == "estimated"
    assert body["pose"]["intrinsics"]["fov_deg"] == pytest.approx(truth.fov_deg, rel=0.03)


async def test_a_distorted_photo_is_solved_through_its_lens(client, engine, catalog):
    lens = LensDistortion(k1=-0.2, k2=0.05)
    camera = TILTED.model_copy(update={"fov_deg": 50.0, "distortion": lens})
    image, truth = target(engine, catalog, "garden", camera)
    intrinsics = {"fov_deg": 50.0, "distortion": lens.model_dump()}
    body = (
        await client.post(
            "/free-pose", json={"scene": "garden", "target": image, "intrinsics": intrinsics}
        )
    ).json()
    assert body["status"] == "found", body["reason"]
    moved, turned = pose_error(body["pose"], truth)
    assert moved < 0.03 * 8.0
    assert turned < 1.5
    assert body["pose"]["intrinsics"]["distortion"] == lens.model_dump()


async def test_a_large_photo_is_judged_in_the_detectors_pixels(client, engine, catalog):
    """The same view in a photo 12.5 times larger (4000 x 3000), its boxes as far off in the
    detector's pixels (320 x 256 input, the photo shrunk into it): with ``detector_input`` it
    gets the small one's answer and confidence, in its own pixels. Taken as the photo's own
    pixels, its box errors (12.5 times the detector's noise) cost it most of its confidence."""
    image, truth = target(engine, catalog, "garden", TILTED)
    rng = np.random.default_rng(3)
    for d in image["detections"]:  # about the detector's box-edge noise, clipped to the film
        d["box"] = list(np.clip(np.add(d["box"], rng.normal(0.0, 1.0, 4)), 0, [W, H, W, H]))
    k = {"fx_px": truth.fx, "fy_px": truth.fy, "cx_px": truth.cx, "cy_px": truth.cy}
    s = 12.5
    large = {
        "image_size": [round(W * s), round(H * s)],
        "detections": [{**d, "box": [v * s for v in d["box"]]} for d in image["detections"]],
    }
    large_k = {name: value * s for name, value in k.items()}

    async def ask(target: dict, intrinsics: dict, detector_input=None) -> dict:
        request = {"scene": "garden", "target": target, "intrinsics": intrinsics}
        answer = await client.post("/free-pose", json={**request, "detector_input": detector_input})
        assert answer.status_code == 200, answer.text
        return answer.json()

    small = await ask(image, k, [320, 256])
    judged = await ask(large, large_k, [320, 256])
    assert small["status"] == judged["status"] == "found", judged["reason"]
    assert judged["pose"]["position"] == pytest.approx(small["pose"]["position"], abs=1e-6)
    assert judged["pose"]["confidence"] == pytest.approx(small["pose"]["confidence"], abs=1e-6)
    assert judged["pose"]["residual_px"] == pytest.approx(small["pose"]["residual_px"] * s)
    assert judged["pose"]["intrinsics"]["fx_px"] == pytest.approx(truth.fx * s)
    assert small["pose"]["confidence"] > 0.5
    as_own_pixels = await ask(large, large_k)
    assert as_own_pixels["pose"]["confidence"] < 0.5 * small["pose"]["confidence"]


async def test_two_detections_are_ambiguous_with_alternatives_and_none_failed(
    client, engine, catalog
):
    image, _ = target(engine, catalog, "garden", TILTED)
    two = {**image, "detections": image["detections"][:2]}
    body = (await client.post("/free-pose", json={"scene": "garden", "target": two})).json()
    assert body["status"] == "ambiguous"
    assert body["ambiguity"] == "few"
    assert body["alternatives"]
    assert body["pose"]["confidence"] <= 0.5
    none = {**image, "detections": []}
    body = (await client.post("/free-pose", json={"scene": "garden", "target": none})).json()
    assert body["status"] == "failed"
    assert body["ambiguity"] is None
    assert body["pose"] is None
    assert body["nearest_grid"] is None
    assert "no object was detected" in body["reason"]


async def test_the_scene_objects_are_built_once_per_scene(app_and_client, engine, catalog):
    app, client = app_and_client
    image, _ = target(engine, catalog, "demo", FreeCamera(position=(5, -4, 5), look_at=(0, 0, 0)))
    cache = app.state.optimizer.free_objects
    await client.post("/free-pose", json={"scene": "demo", "target": image})
    hits = cache.hits
    await client.post("/free-pose", json={"scene": "demo", "target": image})
    assert cache.hits == hits + 1


BALL = {"label": "sphere", "class_id": 0, "confidence": 0.9, "box": [100, 80, 140, 120]}


@pytest.mark.parametrize(
    ("change", "status", "field"),
    [
        ({"scene": "nowhere"}, 404, "scene"),
        (
            {"target": {"image_size": [W, H], "detections": [{**BALL, "box": [0, 0, 400, 10]}]}},
            422,
            "target.detections[0].box",
        ),
        ({"intrinsics": {"fx_px": 300.0}}, 422, "intrinsics"),
        ({"intrinsics": {"fov_deg": 180.0}}, 422, "intrinsics.fov_deg"),
        ({"intrinsics": {"fx_px": 0.5, "fy_px": 0.5}}, 422, "intrinsics.fx_px"),
        (
            {"intrinsics": {"fov_deg": 60.0, "distortion": {"k1": -2.0}}},
            422,
            "intrinsics.distortion.k1",
        ),
        ({"intrinsics": {"distortion": {"k1": 0.1}}}, 422, "intrinsics"),
        (
            {"target": {"image_size": [W, H], "detections": [{**BALL, "box": [1, 2, "x", 4]}]}},
            422,
            "target.detections[0].box",
        ),
        ({"detector_input": [0, 256]}, 422, "detector_input"),
        ({"detector_input": [320]}, 422, "detector_input"),
    ],
)
async def test_bad_requests_are_problems_naming_the_field(client, change, status, field):
    body = {"scene": "demo", "target": {"image_size": [W, H], "detections": [BALL]}, **change}
    answer = await client.post("/free-pose", json=body)
    assert answer.status_code == status, answer.text
    assert answer.headers["content-type"].startswith("application/problem+json")
    problem = answer.json()
    assert problem["field"].startswith(field), problem


def test_a_pose_inside_an_object_is_never_answered(engine, catalog):
    """The renderer refuses a camera inside an object's box, and such a pose is wrong anyway:
    the next alternative takes its place, and with none the answer is failed."""
    image, _ = target(engine, catalog, "garden", TILTED)
    scene = catalog.get("garden")
    objects = scene_objects(scene.spec, scene.assets)
    detections = [Detection.model_validate(d) for d in image["detections"]]
    answer = solve_free_pose(objects, detections, W, H)
    assert answer.pose is not None
    assert _renderable(answer, objects) is answer
    inside = replace(answer.pose, position=tuple(float(v) for v in objects.centroids[0]))
    loose = replace(answer, status="ambiguous", ambiguity="loose")
    promoted = _renderable(replace(loose, pose=inside, alternatives=(answer.pose,)), objects)
    assert promoted.pose == answer.pose
    assert promoted.alternatives == ()
    assert promoted.ambiguity == "rivals"  # one of the poses the boxes allow, not the one
    failed = _renderable(replace(answer, pose=inside, alternatives=()), objects)
    assert failed.status == "failed"
    assert failed.ambiguity is None
    assert failed.pose is None
    assert "inside an object" in failed.reason
