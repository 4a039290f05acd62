"""The renderer as a real uvicorn process over HTTP: ground-truth boxes against the rendered
pixels, and a schema-driven fuzz of every route (no 5xx, answers match the OpenAPI schema)."""

from __future__ import annotations

import cv2
import httpx
import numpy as np
import pytest

from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.common.geometry.grid import grid_for
from services.renderer.client import RendererClient
from tests.support import assert_token_required, fuzz_service

pytestmark = pytest.mark.slow


def srgb8(linear: tuple[float, float, float]) -> np.ndarray:
    c = np.asarray(linear, dtype=np.float64)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def colour_boxes(rgb: np.ndarray, colours: dict[str, tuple[float, float, float]]) -> dict:
    """Boxes of the pixels whose hue is that of each object's colour (independent of the
    renderer's ids: only the image is read)."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(np.int32)
    boxes: dict[str, tuple[float, float, float, float] | None] = {}
    for name, colour in colours.items():
        ref = cv2.cvtColor(srgb8(colour).reshape(1, 1, 3), cv2.COLOR_RGB2HSV)[0, 0].astype(int)
        hue_gap = np.abs(hsv[..., 0] - ref[0])
        hue_gap = np.minimum(hue_gap, 180 - hue_gap)
        mask = ((hue_gap <= 8) & (hsv[..., 1] >= 100) & (hsv[..., 2] >= 25)).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        keep = [i for i in range(1, count) if stats[i, cv2.CC_STAT_AREA] >= 12]
        if not keep:
            boxes[name] = None
            continue
        ys, xs = np.nonzero(np.isin(labels, keep))
        boxes[name] = (xs.min(), ys.min(), xs.max() + 1.0, ys.max() + 1.0)
    return boxes


def iou(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union


def test_annotated_boxes_match_the_rendered_objects(renderer_process):
    """Over real HTTP: every visible ball's annotated box overlaps the box of its coloured pixels
    in the PNG with IoU >= 0.9."""
    url = renderer_process.url
    with httpx.Client(base_url=url, timeout=60.0, headers=renderer_process.headers) as client:
        detail = client.get("/scenes/demo").json()
        colours = {o["name"]: tuple(o["color"]) for o in detail["spec"]["objects"]}
        search = detail["spec"]["search"]
        grid = grid_for(search["angle_step_deg"], search["min_theta_deg"], search["max_theta_deg"])
        rng = np.random.default_rng(2024)
        flats = [0, grid.size - 1, *rng.choice(grid.size, size=10, replace=False)]
        compared = 0
        for flat in flats:
            index = grid.unflat(int(flat))
            body = {"scene": "demo", "pose": {"lat": index.lat, "lon": index.lon}}
            png = client.post("/render", json={**body, "spp": 64})
            assert png.status_code == 200, png.text
            rgb = cv2.cvtColor(
                cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR),
                cv2.COLOR_BGR2RGB,
            )
            ann = client.post("/render/annotations", json=body).json()
            seen = colour_boxes(rgb, colours)
            for obj in ann["objects"]:
                if obj["visible_pixels"] < 100:
                    continue
                found = seen[obj["name"]]
                assert found is not None, (index, obj["name"])
                score = iou(obj["box"], found)
                assert score >= 0.9, (index, obj["name"], obj["box"], found, score)
                compared += 1
        assert compared >= 40


def test_the_renderer_renders_for_holders_of_the_service_token_only(renderer_process):
    body = {"scene": "demo", "pose": {"lat": 2, "lon": 3}, "width": 64, "height": 48, "spp": 1}
    assert_token_required(renderer_process, "POST", "/render", json=body)
    assert_token_required(renderer_process, "GET", "/scenes")


def test_every_route_answers_within_its_schema(renderer_process):
    """Schema-driven fuzzing of every route (see :func:`tests.support.fuzz_service`)."""
    assert (
        fuzz_service(renderer_process.url, max_examples=25, headers=renderer_process.headers) >= 6
    )


@pytest.mark.parametrize(
    "lens", [None, LensDistortion(k1=-0.25, k2=0.05, p1=0.002)], ids=["pinhole", "distorted"]
)
def test_the_client_renders_a_free_camera_with_its_ground_truth(renderer_process, lens):
    """``RendererClient.render_camera`` over real HTTP: the PNG of the film asked for and the
    annotations of the same camera, their boxes on the coloured pixels (also when the image is
    warped through a lens)."""
    camera = FreeCamera(
        position=(4.0, -3.0, 3.5),
        look_at=(0.0, 0.0, 0.4),
        roll_deg=-15.0,
        fov_deg=55.0,
        distortion=lens,
    )
    with RendererClient(renderer_process.url, token=renderer_process.token) as client:
        colours = {o.name: o.color for o in client.scene("demo").spec.objects}
        png, ann = client.render_camera("demo", camera, width=160, height=120, spp=32)
    rgb = cv2.cvtColor(
        cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )
    assert rgb.shape == (120, 160, 3)
    assert ann.pose is None
    assert ann.distortion == lens
    assert ann.camera.fov_deg == pytest.approx(55.0)
    seen = colour_boxes(rgb, colours)
    compared = 0
    for obj in ann.objects:
        if obj.visible_pixels < 60 or obj.box is None:
            continue
        found = seen[obj.name]
        assert found is not None, obj.name
        assert iou(obj.box, found) >= 0.8, (obj.name, obj.box, found)
        compared += 1
    assert compared >= 3
