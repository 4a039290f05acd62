"""The optimizer's HTTP API in process (ASGI transport, lifespan run): answers, a whole search
and problem+json for bad input."""

from __future__ import annotations

from collections.abc import AsyncIterator

import httpx
import pytest

from services.common.geometry.grid import grid_for
from services.common.geometry.pose import GridIndex
from services.optimizer.app import create_app
from services.optimizer.settings import OptimizerSettings
from simulation import SceneSimulator
from tests.support import in_process

pytestmark = pytest.mark.anyio

CAMERA = {"fov_deg": 45, "width": 320, "height": 240, "radius": 8.0}
GRID = {"angle_step_deg": 7.5, "min_theta_deg": 7.5, "max_theta_deg": 82.5}


@pytest.fixture(scope="module")
async def client() -> AsyncIterator[httpx.AsyncClient]:
    settings = OptimizerSettings(optimizer_max_body_bytes=200_000, optimizer_max_grid_poses=5000)
    async with in_process(create_app(settings), "http://optimizer", settings.token()) as c:
        yield c


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    simulator = SceneSimulator.from_scene(scene)
    grid = scene.spec.search.grid()
    views = simulator.grid_views(grid)

    def detections(flat: int, scale: float = 1.0) -> list[dict]:
        out = []
        for d in simulator.detections(simulator.observe(views, flat)):
            body = d.model_dump(mode="json")
            body["box"] = [v * scale for v in body["box"]]
            out.append(body)
        return out

    return grid, detections


def view(grid, detections, flat: int, **pose) -> dict:
    index = grid.unflat(flat)
    return {
        "pose": pose or {"lat": index.lat, "lon": index.lon},
        "image_size": [320, 240],
        "detections": detections(flat),
    }


async def test_health_lists_the_strategies(client):
    body = (await client.get("/health")).json()
    assert body == {
        "status": "ok",
        "service": "optimizer",
        "strategies": ["simple", "paper", "reprojection"],
        "default_strategy": "reprojection",
        "paper_calibrations": 1,
        "target_cache": {  # nothing kept yet
            "targets": 0,
            "bytes": 0,
            "max_bytes": body["target_cache"]["max_bytes"],
            "hits": 0,
            "misses": 0,
        },
    }
    strategies = {s["name"]: s for s in (await client.get("/strategies")).json()}
    assert strategies["reprojection"]["default"]
    assert strategies["paper"]["needs_calibration"]


@pytest.mark.parametrize("strategy", ["simple", "paper", "reprojection"])
async def test_a_whole_search_over_http(client, demo, strategy):
    """Loop the service like a controller would, with simulated detections."""
    grid, detections = demo
    target = grid.flat(GridIndex(lat=6, lon=20))
    history = [view(grid, detections, 12)]
    target_image = {"image_size": [320, 240], "detections": detections(target)}
    for _ in range(30):
        response = await client.post(
            "/next-pose",
            json={
                "scene": "demo",
                "strategy": strategy,
                "target": target_image,
                "history": history,
            },
        )
        assert response.status_code == 200, response.text
        answer = response.json()
        if answer["done"]:
            break
        nxt = answer["next"]["index"]
        history.append(view(grid, detections, grid.flat(GridIndex(**nxt))))
    assert answer["done"]
    assert answer["next"]["index"] == {"lat": 6, "lon": 20}
    assert answer["estimate"]["grid"]["index"] == {"lat": 6, "lon": 20}
    assert 0.0 <= answer["estimate"]["confidence"] <= 1.0
    assert answer["strategy"] == strategy
    assert answer["reason"]


async def test_explicit_camera_and_grid_and_scaled_images(client, demo):
    """No scene: camera and grid in the request; the images are twice the film size."""
    grid, detections = demo
    body = {
        "camera": CAMERA,
        "grid": GRID,
        "target": {"image_size": [640, 480], "detections": detections(200, 2.0)},
        "history": [
            {
                "pose": {"lat": 1, "lon": 2},
                "image_size": [640, 480],
                "detections": detections(grid.flat(GridIndex(lat=1, lon=2)), 2.0),
            },
        ],
    }
    answer = (await client.post("/next-pose", json=body)).json()
    assert answer["next"]["index"] == grid.unflat(200).model_dump()
    assert answer["move"] == "jump"
    assert not answer["ambiguous"]


async def test_history_poses_may_be_given_as_grid_angles(client, demo):
    grid, detections = demo
    pose = grid.pose(grid.unflat(40))
    body = {
        "scene": "demo",
        "target": {"image_size": [320, 240], "detections": detections(40)},
        "history": [view(grid, detections, 40, theta_deg=pose.theta_deg, phi_deg=pose.phi_deg)],
    }
    answer = (await client.post("/next-pose", json=body)).json()
    assert answer["done"]
    assert answer["next"]["index"] == grid.unflat(40).model_dump()


async def test_an_empty_history_gets_a_start_pose(client, demo):
    grid, detections = demo
    body = {"scene": "demo", "target": {"image_size": [320, 240], "detections": detections(9)}}
    answer = (await client.post("/next-pose", json=body)).json()
    assert answer["move"] == "start"
    assert not answer["done"]
    assert answer["estimate"] is None


async def test_a_cycling_search_is_flagged_stuck(client, demo):
    """A proposal already visited three times means the search goes round in circles."""
    grid, detections = demo
    body = {
        "scene": "demo",
        "strategy": "paper",
        "target": {"image_size": [320, 240], "detections": detections(grid.size - 3)},
        "history": [view(grid, detections, 100)],
    }
    first = (await client.post("/next-pose", json=body)).json()
    assert not first["stuck"]
    proposed = grid.flat(GridIndex(**first["next"]["index"]))
    # The paper strategy decides from the current view: back at the start it proposes the same.
    looped = [view(grid, detections, f) for f in [proposed, 100] * 3]
    answer = (
        await client.post("/next-pose", json={**body, "history": body["history"] + looped})
    ).json()
    assert answer["next"] == first["next"]
    assert answer["stuck"]
    assert "going round in circles" in answer["reason"]


async def test_map_returns_ground_positions(client, catalog, demo):
    grid, detections = demo
    flat = 150
    pose = grid.pose(grid.unflat(flat))
    truth = {tuple(o.position) for o in catalog.get("demo").spec.objects}
    for method, tolerance in (("exact", 0.08), ("paper", 0.5)):
        body = {
            "camera": CAMERA,
            "pose": pose.model_dump(),
            "method": method,
            "view": {"image_size": [320, 240], "detections": detections(flat)},
        }
        answer = (await client.post("/map", json=body)).json()
        assert answer["method"] == method
        for obj in answer["objects"]:
            gap = min(abs(complex(*obj["position"]) - complex(*t)) for t in truth)
            assert gap < tolerance, (method, obj)
        if method == "exact":
            assert all(o["reliable"] and o["height"] > 0 for o in answer["objects"])


def bad(demo) -> list[tuple[dict, int, str]]:
    grid, detections = demo
    target = {"image_size": [320, 240], "detections": detections(50)}
    ok = {"scene": "demo", "target": target, "history": [view(grid, detections, 60)]}
    outside = {
        **target,
        "detections": [
            *target["detections"][:2],
            {**target["detections"][2], "box": [300.0, 10.0, 330.0, 40.0]},
        ],
    }
    inverted = {**target, "detections": [{**target["detections"][0], "box": [50, 50, 40, 60]}]}
    wrong_shape = {"image_size": [320, 320], "detections": target["detections"]}
    return [
        ({**ok, "target": outside}, 422, "target.detections[2].box"),
        ({**ok, "target": inverted}, 422, "target.detections[0].box"),
        ({**ok, "target": {**target, "detections": []}}, 422, "target.detections"),
        ({**ok, "target": wrong_shape}, 422, "target.image_size"),
        ({**ok, "strategy": "greedy"}, 422, "strategy"),
        ({**ok, "strategy": None}, 422, "strategy"),
        ({**ok, "scene": "nope"}, 404, "scene"),
        ({**ok, "scene": "../etc"}, 422, "scene"),
        ({"target": target}, 422, "camera"),
        ({"target": target, "camera": CAMERA}, 422, "grid"),
        ({**ok, "camera": {**CAMERA, "fov_deg": 60}}, 422, "camera"),
        ({**ok, "grid": {**GRID, "angle_step_deg": 15}}, 422, "grid"),
        ({**ok, "scene": None, "camera": CAMERA, "grid": {"angle_step_deg": 1.0}}, 422, "grid"),
        (
            {**ok, "scene": None, "camera": CAMERA, "grid": {"angle_step_deg": 0.5}},
            422,
            "grid.angle_step_deg",
        ),
        (
            {**ok, "history": [{**ok["history"][0], "pose": {"lat": 11, "lon": 0}}]},
            422,
            "history[0].pose.lat",
        ),
        (
            {**ok, "history": [{**ok["history"][0], "pose": {"lat": 0, "lon": 6}}]},
            422,
            "history[0].pose.lon",
        ),
        (
            {**ok, "history": [{**ok["history"][0], "pose": {"theta_deg": 31, "phi_deg": 0}}]},
            422,
            "history[0].pose",
        ),
        (
            {**ok, "history": [{**ok["history"][0], "detections": outside["detections"]}]},
            422,
            "history[0].detections[2].box",
        ),
        ({**ok, "tolerances": {"match_rms_px": 0}}, 422, "tolerances.match_rms_px"),
        ({**ok, "colour": 1}, 422, "colour"),
    ]


async def test_bad_requests_get_problem_details_naming_the_field(client, demo):
    for body, status, field in bad(demo):
        if body.get("scene", "") is None:
            body = {k: v for k, v in body.items() if k != "scene"}
        response = await client.post("/next-pose", json=body)
        assert response.status_code == status, (field, response.text)
        assert response.headers["content-type"] == "application/problem+json"
        problem = response.json()
        assert problem["status"] == status
        assert problem["field"] == field, problem


async def test_paper_needs_coefficients_for_the_camera(client, demo):
    grid, detections = demo
    odd = {**CAMERA, "fov_deg": 50}
    body = {
        "camera": odd,
        "grid": GRID,
        "strategy": "paper",
        "target": {"image_size": [320, 240], "detections": detections(50)},
        "history": [view(grid, detections, 60)],
    }
    response = await client.post("/next-pose", json=body)
    assert response.status_code == 422
    assert response.json()["type"] == "urn:cosmos:problem:no-paper-calibration"
    assert (
        await client.post("/next-pose", json={**body, "strategy": "reprojection"})
    ).status_code == 200


async def test_map_rejects_boxes_outside_the_view(client):
    body = {
        "camera": CAMERA,
        "pose": {"theta_deg": 30, "phi_deg": 0},
        "view": {
            "image_size": [320, 240],
            "detections": [
                {"label": "sphere", "class_id": 0, "confidence": 0.9, "box": [0, 0, 400, 10]}
            ],
        },
    }
    response = await client.post("/map", json=body)
    assert response.status_code == 422
    assert response.json()["field"] == "view.detections[0].box"


@pytest.mark.parametrize("content", [b"", b"{", b"[]", b"null", b'{"target": NaN}'])
async def test_malformed_json_is_a_422_problem(client, content):
    response = await client.post(
        "/next-pose", content=content, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422
    assert response.headers["content-type"] == "application/problem+json"


async def test_oversized_body_is_413(client):
    response = await client.post(
        "/next-pose", content=b" " * 300_000, headers={"content-type": "application/json"}
    )
    assert response.status_code == 413


async def test_the_full_pi_over_24_grid_from_the_pole(client, catalog):
    """θ 0–90°: the pole and the horizon ring are poses like any other."""
    scene = catalog.get("demo")
    grid = grid_for(7.5, 0.0, 90.0)
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.grid_views(grid)

    def detections(flat: int) -> list[dict]:
        return [
            d.model_dump(mode="json") for d in simulator.detections(simulator.observe(views, flat))
        ]

    target = grid.flat(GridIndex(lat=12, lon=24))  # on the horizon, opposite φ = 0
    body = {
        "camera": CAMERA,
        "grid": {"angle_step_deg": 7.5, "min_theta_deg": 0, "max_theta_deg": 90},
        "target": {"image_size": [320, 240], "detections": detections(target)},
        "history": [
            {"pose": {"lat": 0, "lon": 0}, "image_size": [320, 240], "detections": detections(0)}
        ],
    }
    simple = (await client.post("/next-pose", json={**body, "strategy": "simple"})).json()
    assert simple["move"] == "S"  # latitude first, one ring at a time
    jump = (await client.post("/next-pose", json=body)).json()
    assert jump["next"]["index"] == {"lat": 12, "lon": 24}
