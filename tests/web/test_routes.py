"""The controller's routes for the page, over HTTP against the real stack: the page's files with
their media types and cache headers, a rendered view of any iteration (kept or rendered again,
the same pixels either way), the target image, any grid pose of a scene, and the ``search``
events a live page follows."""

from __future__ import annotations

import gzip
import json
import re
import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from cosmos.launch import spawn_service, stop_service, wait_healthy
from cosmos.stack import Stack
from services.common.auth import TOKEN_VARIABLE
from services.common.contracts.search import ControllerHealth, Iteration, Search, StageTimings
from services.common.images import encode_ppm
from services.controller.client import ControllerClient
from services.controller.keys import local_key
from services.controller.settings import ControllerSettings
from services.controller.store import open_store, utcnow
from tests.web.conftest import api, render_png

pytestmark = pytest.mark.slow


def pixels(png: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def finished_search(stack, png: bytes, **options):
    with ControllerClient(stack.controller, api_key=stack.api_key) as client:
        search = client.submit(png, "demo", **options)
        for _ in client.follow(search.id, timeout_s=120):
            pass
        return client.get(search.id)


def test_the_page_is_served_with_its_media_types_and_cache_headers(stack):
    index = httpx.get(f"{stack.controller}/", headers={"Accept-Encoding": "identity"})
    assert index.status_code == 200  # no key: the page asks for one
    assert index.headers["content-type"] == "text/html; charset=utf-8"
    assert index.headers["cache-control"] == "no-cache"
    assert "script-src 'self'" in index.headers["content-security-policy"]
    assert index.headers["x-content-type-options"] == "nosniff"
    again = httpx.get(f"{stack.controller}/", headers={"If-None-Match": index.headers["etag"]})
    assert again.status_code == 304
    assert again.content == b""

    assets = re.findall(r'(?:src|href)="(/assets/[^"]+)"', index.text)
    assert {a.rsplit(".", 1)[1] for a in assets} == {"js", "css"}
    for path in assets:
        plain = httpx.get(f"{stack.controller}{path}", headers={"Accept-Encoding": "identity"})
        assert plain.status_code == 200
        assert plain.headers["cache-control"] == "public, max-age=31536000, immutable"
        media = "text/javascript" if path.endswith(".js") else "text/css"
        assert plain.headers["content-type"] == f"{media}; charset=utf-8"
        assert "content-encoding" not in plain.headers
        zipped = httpx.get(f"{stack.controller}{path}", headers={"Accept-Encoding": "gzip"})
        assert zipped.headers["content-encoding"] == "gzip"
        assert zipped.content == plain.content  # httpx inflates it
        assert int(zipped.headers["content-length"]) < len(plain.content)
        assert gzip.decompress(gzip.compress(plain.content)) == plain.content
    # three.js is not in the app: it is the 3D view's worker's, started after the first paint;
    # nothing comes from elsewhere
    js = next(a for a in assets if a.endswith(".js"))
    app = httpx.get(f"{stack.controller}{js}").text
    assert "WebGLRenderer" not in app
    workers = set(re.findall(r"/assets/(hemisphere-worker-[\w-]+\.js)", app))
    assert len(workers) == 1, workers
    worker = httpx.get(f"{stack.controller}/assets/{workers.pop()}")
    assert worker.headers["content-type"] == "text/javascript; charset=utf-8"
    assert "WebGLRenderer" in worker.text
    code = app + worker.text
    assert not re.search(r"""(?:import|from|src=|url\()\s*["']?https?://""", code)

    missing = httpx.get(f"{stack.controller}/assets/nope.js")
    assert missing.status_code == 404
    assert missing.headers["content-type"] == "application/problem+json"


def test_an_iterations_view_is_the_view_the_search_rendered(stack):
    target = render_png(stack, "demo", 4, 10)
    final = finished_search(stack, target, start_theta_deg=60, start_phi_deg=0, seed=1)
    assert final.status == "succeeded", final.error
    spp = ControllerSettings.model_fields["controller_view_spp"].default
    with api(stack) as http:
        for it in final.iterations:
            view = http.get(f"/searches/{final.id}/iterations/{it.index}/view.png")
            assert view.status_code == 200, view.text
            assert view.headers["content-type"] == "image/png"
            # the renderer's own answer for that pose, with the controller's view settings
            direct = render_png(stack, "demo", it.pose.index.lat, it.pose.index.lon, spp=spp)
            assert np.array_equal(pixels(view.content), pixels(direct))
            assert pixels(view.content).shape[1::-1] == tuple(it.image_size)
        beyond = http.get(f"/searches/{final.id}/iterations/{len(final.iterations)}/view.png")
        assert beyond.status_code == 404
        assert beyond.json()["field"] == "index"
        assert http.get("/searches/nope/iterations/0/view.png").status_code == 404
        assert http.get(f"/searches/{final.id}/target").content == target  # a PNG as it came
    refused = httpx.get(f"{stack.controller}/searches/{final.id}/iterations/0/view.png")
    assert refused.status_code == 401


def test_a_view_not_kept_is_rendered_again_identically(stack):
    """Two poses no search visited: rendered on demand, twice the same pixels, and equal to the
    renderer's answer (the view store keeps few views, so a replay renders them again)."""
    spp = ControllerSettings.model_fields["controller_view_spp"].default
    with api(stack) as http:
        first = http.get("/scenes/demo/view.png", params={"lat": 9, "lon": 3})
        assert first.status_code == 200, first.text
        direct = render_png(stack, "demo", 9, 3, spp=spp)
        assert np.array_equal(pixels(first.content), pixels(direct))
        second = http.get("/scenes/demo/view.png", params={"lat": 9, "lon": 3})
        assert second.content == first.content
        off_grid = http.get("/scenes/demo/view.png", params={"lat": 99, "lon": 0})
        assert off_grid.status_code == 422, off_grid.text
        assert off_grid.headers["content-type"] == "application/problem+json"
        unknown = http.get("/scenes/nowhere/view.png", params={"lat": 0, "lon": 0})
        assert unknown.status_code == 404
        assert "nowhere" in unknown.json()["detail"]
        detail = http.get("/scenes/demo").json()
        assert detail["grid"]["size"] == sum(ring["count"] for ring in detail["grid"]["rings"])
        assert http.get("/scenes/nowhere").status_code == 404


def test_a_ppm_target_is_shown_as_png(stack):
    png = render_png(stack, "demo", 5, 20)
    rgb = np.ascontiguousarray(pixels(png)[..., ::-1])
    final = finished_search(stack, encode_ppm(rgb), seed=4)
    with api(stack) as http:
        shown = http.get(f"/searches/{final.id}/target")
    assert shown.headers["content-type"] == "image/png"
    assert np.array_equal(pixels(shown.content), pixels(png))


def test_the_openapi_schema_documents_the_view_routes(stack):
    paths = httpx.get(f"{stack.controller}/openapi.json").json()["paths"]
    view = paths["/searches/{search_id}/iterations/{index}/view.png"]["get"]
    assert "image/png" in view["responses"]["200"]["content"]
    assert {"401", "404", "503"} <= view["responses"].keys()
    assert view["security"] == [{"ApiKey": []}]
    assert "image/png" in paths["/scenes/{scene_id}/view.png"]["get"]["responses"]["200"]["content"]
    assert "/searches/{search_id}/target" in paths
    assert "/" not in paths
    assert not any(p.startswith("/assets") for p in paths)


def test_a_live_search_announces_its_changes_before_it_ends(stack):
    target = render_png(stack, "demo", 3, 7)
    with ControllerClient(stack.controller, api_key=stack.api_key) as client:
        search = client.submit(
            target, "demo", strategy="simple", start_theta_deg=75, start_phi_deg=0, seed=2
        )
    with api(stack) as http:
        events = http.get(f"/searches/{search.id}/events", timeout=120).text
        finished = http.get(f"/searches/{search.id}/events").text
    names = re.findall(r"^event: (\w+)$", events, re.MULTILINE)
    assert names[0] == "search", names
    assert names[-1] == "end", names
    assert names.count("end") == 1
    assert "search" not in re.findall(r"^event: (\w+)$", finished, re.MULTILINE)


# -- a search's own view settings, whatever the controller's now --------------------------------


@contextmanager
def controller_on(stack: Stack, workdir: Path, **settings: str) -> Iterator[tuple[str, str]]:
    """A controller process over ``stack``'s stages with its database in ``workdir`` and the
    view ``settings`` given (``COSMOS_CONTROLLER_VIEW_<NAME>``): its URL and the database's
    local admin key; stopped when the block ends. Two in turn on one ``workdir`` are one
    controller restarted with other settings."""
    database = f"sqlite:///{workdir / 'controller.sqlite3'}"
    env = {
        TOKEN_VARIABLE: stack.service_token or "",
        "COSMOS_CONTROLLER_DATABASE_URL": database,
        "COSMOS_CONTROLLER_RENDERER_URLS": ",".join(stack.renderers),
        "COSMOS_CONTROLLER_DETECTOR_URLS": ",".join(stack.detectors),
        "COSMOS_CONTROLLER_OPTIMIZER_URLS": ",".join(stack.optimizers),
        **{f"COSMOS_CONTROLLER_VIEW_{name.upper()}": value for name, value in settings.items()},
    }
    key = local_key(database)
    controller = spawn_service("services.controller.app:app", workdir / "logs", env=env)
    try:
        wait_healthy(controller, 60.0)
        yield controller.url, key
    finally:
        stop_service(controller)


def view_of(controller: tuple[str, str], search_id: str, index: int) -> np.ndarray:
    """The controller's view of the search's iteration ``index``, as pixels."""
    url, key = controller
    view = httpx.get(
        f"{url}/searches/{search_id}/iterations/{index}/view.png",
        headers={"Authorization": f"Bearer {key}"},
        timeout=60,
    )
    assert view.status_code == 200, view.text
    assert view.headers["content-type"] == "image/png"
    return pixels(view.content)


def test_a_past_search_s_view_keeps_its_own_settings_after_a_restart_with_others(stack, tmp_path):
    """Submitted to a controller that renders views at 4 spp and 160 px, the search records
    those; the controller restarted with its defaults (8 spp, the scene's 320 px) renders the
    search's views again with the search's settings, the very pixels the search saw, while a
    scene view (no search) takes the current ones."""
    target = render_png(stack, "demo", 4, 10)
    with controller_on(stack, tmp_path, spp="4", width="160") as (url, key):
        with ControllerClient(url, api_key=key) as client:
            search = client.submit(
                target, "demo", start_theta_deg=60, start_phi_deg=0, max_iterations=3
            )
            for _ in client.follow(search.id, timeout_s=120):
                pass
            final = client.get(search.id)
    assert final.status == "succeeded", final.error
    assert final.view_settings is not None
    assert (final.view_settings.spp, final.view_settings.width) == (4, 160)
    assert final.iterations
    with controller_on(stack, tmp_path) as restarted:
        for it in final.iterations:
            index = it.pose.index
            own = render_png(stack, "demo", index.lat, index.lon, spp=4, width=160)
            again = view_of(restarted, final.id, it.index)
            assert np.array_equal(again, pixels(own))
            assert again.shape[1::-1] == tuple(it.image_size) == (160, 120)
        url, key = restarted
        scene_view = httpx.get(
            f"{url}/scenes/demo/view.png",
            params={"lat": 4, "lon": 10},
            headers={"Authorization": f"Bearer {key}"},
            timeout=60,
        )
    now = render_png(stack, "demo", 4, 10, spp=8)  # what the restarted controller renders now
    assert np.array_equal(pixels(scene_view.content), pixels(now))


def test_a_search_stored_by_an_earlier_version_renders_with_the_current_settings(stack, tmp_path):
    """A search document without ``view_settings`` (an earlier version's) loads, and its
    views are rendered with the controller's current settings, as before."""
    store = open_store(f"sqlite:///{tmp_path / 'controller.sqlite3'}")
    now = utcnow()
    pose = {"index": {"lat": 3, "lon": 5}, "theta_deg": 30.0, "phi_deg": 75.0}
    search = Search.model_validate(
        {
            "id": "old",
            "status": "succeeded",
            "scene": "demo",
            "strategy": "reprojection",
            "start": pose,
            "seed": 1,
            "max_iterations": 1,
            "created_at": now,
            "updated_at": now,
            "target_size": (320, 240),
        }
    )
    iteration = Iteration.model_validate(
        {
            "index": 0,
            "pose": pose,
            "image_size": (160, 120),
            "detections": (),
            "timings": StageTimings(),
        }
    )
    store.create(search, render_png(stack, "demo", 3, 5))
    store.add_iteration("old", iteration)
    store.close()
    with sqlite3.connect(tmp_path / "controller.sqlite3") as db:  # as an earlier version wrote it
        (doc,) = db.execute("SELECT doc FROM searches WHERE id = 'old'").fetchone()
        old = json.loads(doc)
        assert old.pop("view_settings") is None
        db.execute("UPDATE searches SET doc = ? WHERE id = 'old'", (json.dumps(old),))
    with controller_on(stack, tmp_path, spp="4", width="160") as controller:
        url, key = controller
        with ControllerClient(url, api_key=key) as client:
            loaded = client.get("old")
        assert loaded.view_settings is None
        assert [it.pose.index for it in loaded.iterations] == [iteration.pose.index]
        again = view_of(controller, "old", 0)
    current = render_png(stack, "demo", 3, 5, spp=4, width=160)
    assert np.array_equal(again, pixels(current))


def _next_health(lines: Iterator[str], within_s: float = 30.0) -> dict:
    """The data of the next ``health`` event (keep-alive comments skipped), within ``within_s``."""
    event = ""
    deadline = time.monotonic() + within_s
    for line in lines:
        assert time.monotonic() < deadline, "no health event came"
        if line.startswith("event: "):
            event = line[len("event: ") :]
        elif line.startswith("data: ") and event == "health":
            return json.loads(line[len("data: ") :])
    raise AssertionError("the health events ended")


def test_health_events_push_the_health_at_once_and_when_it_changes_to_anyone(stack):
    blank = cv2.imencode(".png", np.full((240, 320, 3), 128, np.uint8))[1].tobytes()
    with (
        httpx.Client(base_url=stack.controller, timeout=20.0) as anyone,  # no key: as /health
        anyone.stream("GET", "/health/events") as events,
    ):
        assert events.status_code == 200
        assert events.headers["content-type"].startswith("text/event-stream")
        lines = events.iter_lines()
        first = ControllerHealth.model_validate(_next_health(lines))
        polled = httpx.get(f"{stack.controller}/health").json()
        assert [r.name for r in first.replicas] == [r["name"] for r in polled["replicas"]]
        assert first.store_searches is None  # the store's figures are an admin key's
        assert polled["store_searches"] is None
        with api(stack) as http:  # a search that fails at once (nothing to detect) is stored
            assert isinstance(http.get("/health").json()["store_searches"], int)  # admin key
            refused = http.post(
                "/searches?scene=demo", content=blank, headers={"Content-Type": "image/png"}
            )
            assert refused.status_code in {202, 422}, refused.text
        for _ in range(20):  # pushed without asking again, within the read timeout
            now = ControllerHealth.model_validate(_next_health(lines))
            if now.replicas != first.replicas:  # the detector served the search
                break
        else:
            raise AssertionError("no health event showed the search")
