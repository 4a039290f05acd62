"""The renderer's HTTP API in process (ASGI transport, lifespan run): answers and problem+json."""

from __future__ import annotations

from collections.abc import AsyncIterator

import cv2
import httpx
import numpy as np
import pytest
from pydantic import ValidationError

from services.common.contracts.render import SceneDetail
from services.common.images import decode_image
from services.renderer.app import create_app
from services.renderer.depth import DepthImage
from services.renderer.settings import RendererSettings
from tests.support import in_process

pytestmark = pytest.mark.anyio


@pytest.fixture(scope="module")
async def client() -> AsyncIterator[httpx.AsyncClient]:
    settings = RendererSettings(renderer_max_side=1024, renderer_max_body_bytes=4096)
    async with in_process(create_app(settings), "http://renderer", settings.token()) as c:
        yield c


def decode(png: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


async def test_health_reports_the_variant(client):
    body = (await client.get("/health")).json()
    assert body["status"] == "ok"
    assert body["variant"] in {"llvm_ad_rgb", "scalar_rgb"}
    assert body["scenes_available"] >= 2
    assert body["in_flight"] == 0


async def test_scenes_lists_the_built_in_scenes(client):
    scenes = {s["id"]: s for s in (await client.get("/scenes")).json()}
    assert {"demo", "garden"} <= set(scenes)
    assert scenes["demo"]["objects"] == 5


async def test_scene_detail_has_spec_and_grid(client):
    body = (await client.get("/scenes/demo")).json()
    assert body["spec"]["camera"]["fov_deg"] == 45
    rings = body["grid"]["rings"]
    assert rings[0]["theta_deg"] == 7.5
    assert rings[-1]["theta_deg"] == 82.5
    assert body["grid"]["size"] == sum(r["count"] for r in rings)
    detail = SceneDetail.model_validate(body)  # what a client reads back
    assert detail.grid == detail.spec.search
    assert detail.model_dump(mode="json") == body


@pytest.mark.parametrize(
    ("key", "value"), [("size", 3), ("rings", [{"lat": 0, "theta_deg": 7.5, "count": 1}])]
)
async def test_a_scene_detail_read_back_must_agree_with_its_grid(client, key, value):
    body = (await client.get("/scenes/demo")).json()
    body["grid"][key] = value
    with pytest.raises(ValidationError, match=f"{key} does not follow from the step"):
        SceneDetail.model_validate(body)


async def test_scene_schema_is_published(client):
    schema = (await client.get("/schemas/scene.json")).json()
    assert set(schema["required"]) >= {"camera", "lighting", "ground", "objects"}


@pytest.mark.parametrize(
    "pose", [{"theta_deg": 45, "phi_deg": 30}, {"lat": 3, "lon": 5}, {"theta_deg": 0, "phi_deg": 0}]
)
async def test_render_returns_a_png_of_the_scene_size(client, pose):
    response = await client.post("/render", json={"scene": "demo", "pose": pose, "spp": 2})
    assert response.status_code == 200
    assert response.headers["content-type"] == "image/png"
    assert decode(response.content).shape == (240, 320, 3)


async def test_grid_poses_are_resolved_and_reported(client):
    response = await client.post(
        "/render", json={"scene": "demo", "pose": {"lat": 3, "lon": 5}, "spp": 1}
    )
    assert response.headers["x-grid-index"] == "3,5"
    assert float(response.headers["x-pose-theta-deg"]) == pytest.approx(30.0)
    off_grid = await client.post(
        "/render", json={"scene": "demo", "pose": {"theta_deg": 31, "phi_deg": 2}, "spp": 1}
    )
    assert "x-grid-index" not in off_grid.headers


async def test_width_alone_keeps_the_aspect_ratio(client):
    response = await client.post(
        "/render", json={"scene": "demo", "pose": {"lat": 0, "lon": 0}, "width": 160, "spp": 1}
    )
    assert decode(response.content).shape == (120, 160, 3)


async def test_seed_makes_renders_repeatable(client):
    body = {"scene": "demo", "pose": {"lat": 2, "lon": 1}, "spp": 2, "seed": 5}
    first = await client.post("/render", json=body)
    again = await client.post("/render", json=body)
    other = await client.post("/render", json={**body, "seed": 6})
    assert np.array_equal(decode(first.content), decode(again.content))
    assert not np.array_equal(decode(first.content), decode(other.content))


@pytest.mark.parametrize(
    ("accept", "media_type"),
    [
        ("image/x-portable-pixmap", "image/x-portable-pixmap"),
        ("image/x-portable-pixmap, image/png;q=0.5", "image/x-portable-pixmap"),
        ("image/png", "image/png"),
        ("*/*", "image/png"),
    ],
)
async def test_accept_chooses_ppm_or_png_with_the_same_pixels(client, accept, media_type):
    body = {"scene": "demo", "pose": {"lat": 2, "lon": 1}, "spp": 2, "seed": 5}
    png = await client.post("/render", json=body)
    response = await client.post("/render", json=body, headers={"Accept": accept})
    assert response.status_code == 200
    assert response.headers["content-type"] == media_type
    rgb = decode_image(response.content, max_pixels=10**6, max_side=1024)
    assert np.array_equal(rgb[..., ::-1], decode(png.content))


async def test_annotations_match_the_requested_view(client):
    body = {"scene": "garden", "pose": {"lat": 4, "lon": 7}}
    ann = (await client.post("/render/annotations", json=body)).json()
    assert ann["grid_index"] == {"lat": 4, "lon": 7}
    assert ann["camera"]["width"] == 320
    assert ann["camera"]["fx"] == pytest.approx(386.27, abs=0.01)
    assert {o["name"] for o in ann["objects"]} == {"red", "crate", "post", "duck", "hat", "arch"}


BAD_REQUESTS = [
    ({"scene": "nope", "pose": {"lat": 0, "lon": 0}}, 404, "scene"),
    ({"scene": "demo", "pose": {"theta_deg": 95, "phi_deg": 0}}, 422, "pose.theta_deg"),
    ({"scene": "demo", "pose": {"theta_deg": -1, "phi_deg": 0}}, 422, "pose.theta_deg"),
    ({"scene": "demo", "pose": {"theta_deg": 10}}, 422, "pose"),
    ({"scene": "demo", "pose": {"theta_deg": 10, "phi_deg": 0, "lat": 1, "lon": 1}}, 422, "pose"),
    ({"scene": "demo", "pose": {"lat": 11, "lon": 0}}, 422, "pose.lat"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 9}}, 422, "pose.lon"),
    ({"scene": "demo", "pose": {"lat": -1, "lon": 0}}, 422, "pose.lat"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "width": 5000}, 422, "width"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "height": 1}, 422, "height"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "spp": 100000}, 422, "spp"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "spp": 0}, 422, "spp"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "colour": 1}, 422, "colour"),
    ({"scene": "demo", "pose": {"lat": 0, "lon": 0}, "seed": -3}, 422, "seed"),
    ({"pose": {"lat": 0, "lon": 0}}, 422, "scene"),
]


@pytest.mark.parametrize(("body", "status", "field"), BAD_REQUESTS)
@pytest.mark.parametrize("path", ["/render", "/render/annotations", "/render/depth"])
async def test_bad_requests_get_problem_details_naming_the_field(client, path, body, status, field):
    response = await client.post(path, json=body)
    assert response.status_code == status
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert problem["status"] == status
    assert problem["type"].startswith("urn:cosmos:problem:")
    assert problem["field"] == field, problem


async def test_a_render_over_the_sample_cap_names_the_limit(client):
    """A render's cost is its samples (pixels x spp); one request may trace at most 2**26."""
    body = {"scene": "demo", "pose": {"lat": 0, "lon": 0}, "width": 1024, "height": 1024}
    response = await client.post("/render", json={**body, "spp": 128})
    assert response.status_code == 422
    problem = response.json()
    assert (problem["type"], problem["field"]) == ("urn:cosmos:problem:too-many-samples", "spp")
    assert problem["limit"] == 2**26
    assert "COSMOS_RENDERER_MAX_SAMPLES" in problem["detail"]


@pytest.mark.parametrize(
    "content",
    [b"", b"{", b"[]", b"null", b'{"scene": "demo", "pose": {"theta_deg": NaN, "phi_deg": 0}}'],
)
async def test_malformed_json_is_a_422_problem(client, content):
    response = await client.post(
        "/render", content=content, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422
    assert response.headers["content-type"] == "application/problem+json"


async def test_unknown_scene_detail_is_404(client):
    response = await client.get("/scenes/nope")
    assert response.status_code == 404
    assert response.json()["type"] == "urn:cosmos:problem:unknown-scene"


async def test_unknown_route_is_a_problem(client):
    response = await client.get("/nowhere")
    assert response.status_code == 404
    assert response.headers["content-type"] == "application/problem+json"


async def test_oversized_body_is_413_by_content_length(client):
    response = await client.post(
        "/render", content=b"x" * 5000, headers={"content-type": "application/json"}
    )
    assert response.status_code == 413
    assert response.json()["type"] == "urn:cosmos:problem:payload-too-large"


async def test_oversized_streamed_body_is_413(client):
    async def chunks() -> AsyncIterator[bytes]:
        for _ in range(10):
            yield b" " * 1000

    response = await client.post(
        "/render", content=chunks(), headers={"content-type": "application/json"}
    )
    assert response.status_code == 413
    assert response.headers["content-type"] == "application/problem+json"


# -- free cameras -------------------------------------------------------------------------------

NADIR = {"position": [0.3, 0.2, 7.0], "yaw_deg": 0, "pitch_deg": 90}


async def test_a_free_camera_renders_and_annotates(client):
    camera = {**NADIR, "roll_deg": 20, "fx_px": 120, "fy_px": 120, "cx_px": 70, "cy_px": 55}
    body = {"scene": "demo", "camera": camera, "width": 160, "height": 120, "spp": 2}
    response = await client.post("/render", json=body)
    assert response.status_code == 200, response.text
    assert decode(response.content).shape == (120, 160, 3)
    assert "x-pose-theta-deg" not in response.headers
    ann = (await client.post("/render/annotations", json=body)).json()
    assert ann["pose"] is None
    assert ann["grid_index"] is None
    assert ann["distortion"] is None
    assert (ann["camera"]["fx"], ann["camera"]["cx"], ann["camera"]["cy"]) == (120, 70, 55)
    assert sum(o["box"] is not None for o in ann["objects"]) >= 3


async def test_a_distorted_free_camera_reports_its_lens(client):
    lens = {"k1": -0.2, "k2": 0.03, "p1": 0.001, "p2": 0.0, "k3": -0.01}
    body = {"scene": "demo", "camera": {**NADIR, "distortion": lens}, "width": 96, "spp": 1}
    response = await client.post("/render", json=body)
    assert response.status_code == 200, response.text
    assert decode(response.content).shape == (72, 96, 3)
    ann = (await client.post("/render/annotations", json=body)).json()
    assert ann["distortion"] == lens


async def test_depth_is_the_distance_along_the_optical_axis_with_the_objects_masks(client):
    """Straight down from 6 units over the ground: the ground's depth is 6 on every pixel,
    a ball of radius 0.45 (the top 0.9 above the ground) comes 0.9 closer, and the object ids
    cover the same pixels as the annotated visible boxes."""
    camera = {"position": [0.0, 0.0, 6.0], "yaw_deg": 0.0, "pitch_deg": 90.0}
    body = {"scene": "demo", "camera": camera, "width": 160, "height": 120}
    response = await client.post("/render/depth", json=body)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/x-npz"
    image = DepthImage.from_npz(response.content)
    assert image.depth.shape == image.objects.shape == (120, 160)
    ground = image.objects == -1
    assert np.allclose(image.depth[ground], 6.0, atol=1e-4)
    assert image.depth[~ground].min() == pytest.approx(5.1, abs=0.01)
    ann = (await client.post("/render/annotations", json=body)).json()
    for index, obj in enumerate(ann["objects"]):
        ys, xs = np.nonzero(image.objects == index)
        if obj["box"] is None:
            assert xs.size == 0
        else:
            assert [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1] == obj["box"]


async def test_one_render_call_gives_the_colours_with_the_depth(client):
    """``Accept: application/x-npz`` on /render: the very pixels /render gives, and the depth
    and object ids /render/depth gives, in one archive."""
    camera = {"position": [-3.5, 3.0, 4.5], "look_at": [0.3, -0.4, 0.0], "roll_deg": 12.0}
    body = {"scene": "demo", "camera": camera, "width": 160, "height": 120, "spp": 2}
    response = await client.post("/render", json=body, headers={"Accept": "application/x-npz"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/x-npz"
    both = DepthImage.from_npz(response.content)
    png = (await client.post("/render", json=body)).content
    depth = DepthImage.from_npz((await client.post("/render/depth", json=body)).content)
    assert both.rgb is not None
    assert np.array_equal(both.rgb, decode(png)[..., ::-1])  # decode gives BGR
    assert np.array_equal(both.depth, depth.depth)
    assert np.array_equal(both.objects, depth.objects)


def free(**camera):
    return {"scene": "demo", "camera": {**NADIR, **camera}, "width": 96, "spp": 1}


BAD_FREE_CAMERAS = [
    (free(position=[0.0, 0.0, -1.0]), "camera.position", "camera-below-ground"),
    (free(position=[0.0, 0.0, 0.0]), "camera.position", "camera-below-ground"),
    # Inside the red ball's bounding box (centre (1.2, -0.6, 0.45), radius 0.45).
    (free(position=[1.2, -0.6, 0.3]), "camera.position", "camera-inside-object"),
    (
        {"scene": "demo", "camera": {"position": [1, 1, 2], "quaternion_wxyz": [0, 0, 0, 0]}},
        "camera.quaternion_wxyz",
        "invalid-request",
    ),
    (free(fov_deg=0), "camera.fov_deg", "invalid-request"),
    (free(fov_deg=180), "camera.fov_deg", "invalid-request"),
    (free(fx_px=0, fy_px=100), "camera.fx_px", "invalid-request"),
    (free(fx_px=100, fy_px=-5), "camera.fy_px", "invalid-request"),
    (free(fx_px=1e-9, fy_px=1e-9), "camera.fx_px", "field-of-view-too-wide"),
    (free(fx_px=1e5, fy_px=1), "camera.fy_px", "film-too-large"),
    (free(distortion={"k1": -0.6}), "camera.distortion.k1", "distortion-folds-image"),
    # A barrel lens over a 1000 px film is rendered on a pinhole film wider than the 1024 px cap.
    (
        {**free(fov_deg=120, distortion={"k1": -0.02}), "width": 1000},
        "camera.distortion",
        "film-too-large",
    ),
    (free(distortion={"k1": -0.1, "k2": -2.0}), "camera.distortion.k1", "distortion-folds-image"),
    (
        {"scene": "demo", "camera": {"position": [1, 1, 2], "look_at": [1, 1, 2]}},
        "camera.look_at",
        "invalid-request",
    ),
    (free(yaw_deg=None), "camera", "invalid-request"),  # null is "not given": no yaw
    (free(look_at=[0, 0, 0]), "camera", "invalid-request"),
    (free(pitch_deg=95), "camera.pitch_deg", "invalid-request"),
    (free(colour=1), "camera.colour", "invalid-request"),
    ({**free(), "pose": {"lat": 0, "lon": 0}}, "body", "invalid-request"),
    ({"scene": "demo"}, "body", "invalid-request"),
]


@pytest.mark.parametrize(("body", "field", "slug"), BAD_FREE_CAMERAS)
@pytest.mark.parametrize("path", ["/render", "/render/annotations", "/render/depth"])
async def test_bad_free_cameras_get_problem_details_naming_the_field(
    client, path, body, field, slug
):
    response = await client.post(path, json=body)
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert (problem["field"], problem["type"]) == (field, f"urn:cosmos:problem:{slug}"), problem


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity"])
async def test_non_finite_camera_numbers_are_422_naming_the_field(client, bad):
    content = (
        '{"scene": "demo", "camera": {"position": [0, ' + bad + ', 5], "yaw_deg": 0, '
        '"pitch_deg": 90}}'
    )
    response = await client.post(
        "/render", content=content, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422
    assert response.json()["field"] == "camera.position[1]"
