"""The start pose predicted from the target's boxes alone (services.optimizer.start_pose): against
the renderer's ground truth on the demo scene's grid (its annotations, as a perfect detector
would draw the boxes, rendered by the real engine), a symmetric layout that must be called
ambiguous, the cache, and ``POST /start-pose`` in process with its problem+json refusals."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from services.common.geometry.pose import GridIndex
from services.common.geometry.scene import LoadedScene, SceneSpec
from services.common.scene_models import object_classes
from services.optimizer.app import create_app
from services.optimizer.free import scene_objects
from services.optimizer.observations import Observation
from services.optimizer.settings import OptimizerSettings
from services.optimizer.start_pose import GridViewCache, GridViews, predict_start
from tests.support import in_process

MIN_VISIBLE = 0.6


def rendered_target(engine, scene: LoadedScene, flat: int, identity: bool) -> Observation:
    """The boxes of the objects the real engine shows at grid pose ``flat`` (those at least
    60 % visible), labelled as the scene's own detector (``identity``) or the general one."""
    grid = scene.spec.search.grid()
    index = grid.unflat(flat)
    camera = scene.spec.camera
    annotations = engine.annotate(scene, grid.pose(index), camera.width, camera.height, index)
    objects = scene_objects(scene.spec, scene.assets)
    kept = [
        (i, obj.box)
        for i, obj in enumerate(annotations.objects)
        if obj.box is not None and obj.visible_fraction >= MIN_VISIBLE
    ]
    labels = [(objects.labels if identity else objects.shapes)[i] for i, _ in kept]
    classes = None
    if identity:
        classes = {c.label: "sphere" for c in object_classes(scene.spec)}
    return Observation.from_arrays(labels, [box for _, box in kept], classes=classes)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def demo_views(catalog):
    scene = catalog.get("demo")
    grid = scene.spec.search.grid()
    return (
        scene,
        grid,
        GridViews.of(scene_objects(scene.spec, scene.assets), grid, scene.spec.camera),
    )


# lat 0 is the ring nearest the zenith (θ = 7.5°), where a change of φ turns the whole image.
POSES = [GridIndex(lat=0, lon=0), GridIndex(lat=0, lon=4), GridIndex(lat=1, lon=7)]
POSES += [GridIndex(lat=4, lon=13), GridIndex(lat=7, lon=30), GridIndex(lat=10, lon=45)]


@pytest.mark.parametrize("identity", [False, True], ids=["general", "own-detector"])
@pytest.mark.parametrize("index", POSES, ids=lambda i: f"lat{i.lat}-lon{i.lon}")
def test_the_predicted_pose_is_the_true_grid_pose(engine, demo_views, index, identity):
    scene, grid, views = demo_views
    flat = grid.flat(index)
    prediction = predict_start(views, grid, rendered_target(engine, scene, flat, identity))
    assert prediction.status == "found", prediction.reason
    assert prediction.flat == flat, (grid.unflat(prediction.flat or 0), prediction.reason)
    assert prediction.rms_px is not None
    assert prediction.rms_px < 2.0


def test_every_exact_grid_view_predicts_its_own_pose(demo_views):
    """The scene's own projected boxes at every pose (including the zenith ring) give that pose:
    no two grid poses of the demo scene look alike."""
    _, grid, views = demo_views
    for flat in range(grid.size):
        seen = views.expected[flat]
        target = Observation.from_arrays(["sphere"] * int(seen.sum()), views.boxes[flat][seen])
        prediction = predict_start(views, grid, target)
        assert (prediction.status, prediction.flat) == ("found", flat), prediction.reason


def symmetric_scene() -> LoadedScene:
    """Four equal spheres on a square about the centre: turning the camera by a quarter or half
    turn about the vertical axis gives the same image."""
    balls = [
        {
            "name": f"b{i}",
            "shape": "sphere",
            "position": xy,
            "radius": 0.45,
            "color": [0.8, 0.1, 0.1],
        }
        for i, xy in enumerate([[1.5, 1.5], [-1.5, 1.5], [-1.5, -1.5], [1.5, -1.5]])
    ]
    data = {
        "camera": {"fov_deg": 45, "width": 320, "height": 240, "radius": 8.0},
        "lighting": {"point": {"position": [0, 0, 8], "intensity": 100}},
        "ground": {"size": 12.0, "color": [0.5, 0.5, 0.5]},
        "objects": balls,
        "search": {"angle_step_deg": 7.5, "min_theta_deg": 7.5, "max_theta_deg": 82.5},
    }
    return LoadedScene("square", Path("square.yaml"), SceneSpec.model_validate(data), {})


@pytest.mark.parametrize("index", [GridIndex(lat=2, lon=0), GridIndex(lat=6, lon=10)])
def test_a_symmetric_layout_is_ambiguous(index):
    scene = symmetric_scene()
    grid = scene.spec.search.grid()
    views = GridViews.of(scene_objects(scene.spec), grid, scene.spec.camera)
    flat = grid.flat(index)
    seen = views.expected[flat]
    target = Observation.from_arrays(["sphere"] * int(seen.sum()), views.boxes[flat][seen])
    prediction = predict_start(views, grid, target)
    assert prediction.status == "ambiguous", prediction.reason
    # the square's half turn at least (quarter turns fall on the grid when a ring's count does)
    assert prediction.alternatives
    assert "distant pose" in prediction.reason


def test_a_target_the_layout_does_not_explain_fails(demo_views):
    _, grid, views = demo_views
    # three boxes far from anything the five balls show from any pose, one pairable
    flat = grid.flat(GridIndex(lat=5, lon=5))
    seen = np.flatnonzero(views.expected[flat])[:1]
    boxes = np.vstack(
        [views.boxes[flat][seen], [[0, 0, 300, 10], [0, 200, 10, 240], [300, 0, 320, 240]]]
    )
    prediction = predict_start(views, grid, Observation.from_arrays(["sphere"] * 4, boxes))
    assert prediction.status == "failed", prediction.reason


def test_the_grid_views_are_projected_once_per_scene(catalog):
    scene = catalog.get("garden")
    grid = scene.spec.search.grid()
    cache = GridViewCache()
    built = []

    def objects():
        built.append(1)
        return scene_objects(scene.spec, scene.assets)

    first = cache.get(("garden", scene.version), objects, grid, scene.spec.camera)
    again = cache.get(("garden", scene.version), objects, grid, scene.spec.camera)
    assert again is first
    assert len(built) == 1
    assert (cache.hits, cache.misses) == (1, 1)


# -- POST /start-pose ------------------------------------------------------------------------


@pytest.fixture(scope="module")
async def client() -> AsyncIterator[httpx.AsyncClient]:
    settings = OptimizerSettings(optimizer_max_body_bytes=200_000)
    async with in_process(create_app(settings), "http://optimizer", settings.token()) as c:
        yield c


def target_body(views: GridViews, flat: int, labels=None) -> dict:
    seen = np.flatnonzero(views.expected[flat])
    return {
        "image_size": [640, 480],  # twice the camera's film: boxes are scaled to it
        "detections": [
            {
                "label": (labels or views.shapes)[j],
                "class_id": 0,
                "confidence": 0.9,
                "box": [float(v) * 2 for v in views.boxes[flat, j]],
            }
            for j in seen
        ],
    }


@pytest.mark.anyio
async def test_the_route_answers_the_pose(client, demo_views):
    scene, grid, views = demo_views
    flat = grid.flat(GridIndex(lat=3, lon=9))
    response = await client.post(
        "/start-pose", json={"scene": "demo", "target": target_body(views, flat)}
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["status"] == "found", body
    assert body["pose"]["index"] == {"lat": 3, "lon": 9}
    classes = [c.model_dump() for c in object_classes(scene.spec)]
    own = {
        "scene": "demo",
        "target": target_body(views, flat, views.labels),
        "object_classes": classes,
    }
    body = (await client.post("/start-pose", json=own)).json()
    assert (body["status"], body["pose"]["index"]) == ("found", {"lat": 3, "lon": 9})


@pytest.mark.anyio
async def test_bad_start_pose_requests_are_problems_naming_the_field(client, demo_views):
    scene, grid, views = demo_views
    ok = target_body(views, grid.flat(GridIndex(lat=3, lon=9)))
    classes = [c.model_dump() for c in object_classes(scene.spec)]
    outside = {**ok, "detections": [{**ok["detections"][0], "box": [600, 10, 700, 20]}]}
    cases = [
        ({"scene": "nowhere", "target": ok}, 404, "scene"),
        ({"scene": "demo", "target": {**ok, "image_size": [640, 640]}}, 422, "target.image_size"),
        ({"scene": "demo", "target": outside}, 422, "target.detections[0].box"),
        ({"scene": "demo", "target": {**ok, "detections": []}}, 422, "target.detections"),
        (
            {"scene": "demo", "target": ok, "object_classes": classes},
            422,
            "target.detections[0].label",
        ),
        ({"scene": "demo", "target": ok, "object_classes": None}, 422, "object_classes"),
        ({"target": ok}, 422, "scene"),
    ]
    for body, status, field in cases:
        response = await client.post("/start-pose", json=body)
        assert response.status_code == status, (field, response.text)
        assert response.headers["content-type"] == "application/problem+json"
        assert response.json()["field"] == field, response.json()


def test_on_a_fine_grid_near_poses_are_no_rivals(catalog):
    """At 3° the poses a couple of steps from the zenith look almost alike (4.5° away, beyond
    1.5 steps); they are not a distant rival (MIN_RIVAL_DEG), so the prediction stays found."""
    from services.common.geometry.grid import grid_for

    scene = catalog.get("demo")
    grid = grid_for(3.0, 3.0, 87.0)
    views = GridViews.of(scene_objects(scene.spec), grid, scene.spec.camera)
    for index in (GridIndex(lat=0, lon=0), GridIndex(lat=1, lon=1), GridIndex(lat=4, lon=0)):
        flat = grid.flat(index)
        seen = views.expected[flat]
        target = Observation.from_arrays(["sphere"] * int(seen.sum()), views.boxes[flat][seen])
        prediction = predict_start(views, grid, target)
        assert (prediction.status, prediction.flat) == ("found", flat), prediction.reason
