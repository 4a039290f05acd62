"""End to end: the four real services as separate processes on loopback, searches over HTTP.

Targets are rendered by the renderer at random grid poses; the controller must find each
target's grid pose. Also: the public API's answers to bad input, cancelling, the plots, the
stages serving the controller (with the stack's service token) and no stranger, the probes, a
controller killed mid-search that finishes the search after it comes back, and a renderer
killed under ``cosmos up``'s supervision that comes back while the other serves. Every call to
the controller carries the stack's local API key, as the demo's do.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest

from cosmos.launch import free_port, spawn_service, stop_service, wait_healthy
from cosmos.stack import Stack, plan_local_stack, plan_stack, running_stack
from services.common.auth import bearer
from services.common.contracts.render import RenderRequest
from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.images import encode_ppm
from services.controller.client import ControllerClient
from services.controller.grid_edges import STEEP_THETA_DEG
from services.controller.keys import local_key
from services.controller.settings import ControllerSettings
from services.renderer.client import RendererClient
from tests.support import e2e_stack, fuzz_service

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with e2e_stack(tmp_path_factory.mktemp("stack")) as running:
        yield running


def auth(stack: Stack) -> dict[str, str]:
    """The header that carries the stack's API key."""
    return {"Authorization": f"Bearer {stack.api_key}"}


def controller_client(stack: Stack) -> ControllerClient:
    return ControllerClient(stack.controller, api_key=stack.api_key)


def render(stack: Stack, scene: str, lat: int, lon: int) -> bytes:
    with RendererClient(stack.renderers[0], token=stack.service_token) as client:
        return client.render_png(RenderRequest(scene=scene, pose=PoseQuery(lat=lat, lon=lon)))


def run_search(stack: Stack, image: bytes, scene: str, **options):
    with controller_client(stack) as client:
        search = client.submit(image, scene, **options)
        for _ in client.follow(search.id, timeout_s=300):
            pass
        return client.get(search.id)


def grid_of(stack: Stack, scene: str):
    from services.common.geometry.grid import grid_for

    url = f"{stack.renderers[0]}/scenes/{scene}"
    detail = httpx.get(url, headers=bearer(stack.service_token)).json()["spec"]["search"]
    return grid_for(detail["angle_step_deg"], detail["min_theta_deg"], detail["max_theta_deg"])


@pytest.mark.parametrize(("scene", "count"), [("demo", 5), ("garden", 2)])
def test_searches_find_the_targets_grid_pose(stack, scene, count):
    """Without a start: the controller predicts it from the target's detections, and the
    search ends after that one render. A target near the zenith among them: looking that
    steeply down, the views' confirmation is checked by one render more, with its depth, whose
    edges keep the answer (``grid_edges.steep``)."""
    grid = grid_of(stack, scene)
    rng = np.random.default_rng(99 if scene == "demo" else 7)
    near_zenith = grid.flat(GridIndex(lat=0, lon=2))
    for flat in [near_zenith, *rng.choice(grid.size, size=count - 1, replace=False)]:
        target = grid.unflat(int(flat))
        image = render(stack, scene, target.lat, target.lon)
        final = run_search(stack, image, scene, seed=int(flat))
        assert final.status == "succeeded", (target, final.error)
        assert not final.start_given
        result = final.result
        assert result is not None
        assert result.confirmed, result
        assert result.pose.index == target, (target, result)
        views = {(i.pose.index.lat, i.pose.index.lon) for i in final.iterations}
        assert len(views) == 1, (target, final.iterations)
        checked = result.pose.theta_deg < STEEP_THETA_DEG
        assert (result.refit_timings is not None) is checked, result
        assert result.renders == 1 + checked, (target, result)
        if checked:
            assert result.reason.endswith("nearest this grid pose"), result.reason
        assert [i.index for i in final.iterations] == list(range(len(final.iterations)))


def test_an_unconfirmed_answer_is_settled_by_the_render_s_edges(stack):
    """A demo target between grid poses, nearest lat 4, searched for one view from lat 3: the
    search runs out of views, unconfirmed, at lat 3. One render more, with its depth, at that
    pose, and the dense fit from it, puts the camera within 0.5° of the target's: the answer is
    the target's nearest grid pose, still unconfirmed."""
    grid = grid_of(stack, "demo")
    truth = GridIndex(lat=4, lon=5)
    on_grid = grid.pose(truth)
    theta, phi = on_grid.theta_deg + 1.5, on_grid.phi_deg + 2.0
    assert grid.nearest(Pose(theta_deg=theta, phi_deg=phi)) == truth
    with RendererClient(stack.renderers[0], token=stack.service_token) as client:
        query = PoseQuery(theta_deg=theta, phi_deg=phi)
        image = client.render_png(RenderRequest(scene="demo", pose=query))
    start = grid.pose(grid.nearest(Pose(theta_deg=on_grid.theta_deg - 7.5, phi_deg=phi)))
    final = run_search(
        stack,
        image,
        "demo",
        start_theta_deg=start.theta_deg,
        start_phi_deg=start.phi_deg,
        max_iterations=1,
    )
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert [i.pose.index.lat for i in final.iterations] == [3]
    assert not result.confirmed
    assert result.pose.index == truth, result.reason
    assert abs(result.refined_pose.theta_deg - theta) < 0.5, result.refined_pose
    assert abs(result.refined_pose.phi_deg - phi) < 0.5, result.refined_pose
    assert result.renders == 2
    assert "the render's edges put the camera at" in result.reason


@pytest.mark.parametrize("strategy", ["paper", "simple"])
def test_the_papers_strategies_run_end_to_end(stack, strategy):
    image = render(stack, "demo", 3, 7)
    final = run_search(
        stack,
        image,
        "demo",
        strategy=strategy,
        start_theta_deg=45,
        start_phi_deg=200,
        max_iterations=60,
    )
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed, final.result
    assert final.result is not None
    assert final.result.pose.index.lat == 3
    assert final.result.pose.index.lon == 7


def test_a_jpeg_target_is_accepted(stack):
    png = render(stack, "demo", 5, 20)
    rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    ok, jpeg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    final = run_search(stack, bytes(jpeg), "demo", seed=3)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed, final.result
    assert final.result.pose.index.lat == 5
    assert final.result.pose.index.lon == 20


def test_a_ppm_target_is_accepted_and_an_empty_one_fails_clearly(stack):
    png = render(stack, "demo", 4, 7)
    rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    final = run_search(stack, encode_ppm(np.ascontiguousarray(rgb)), "demo", seed=4)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed, final.result
    assert (final.result.pose.index.lat, final.result.pose.index.lon) == (4, 7)

    bare = np.full((240, 320, 3), 128, np.uint8)  # ground only: nothing to search for
    failed = run_search(stack, encode_ppm(bare), "demo", seed=4)
    assert failed.status == "failed"
    assert failed.error is not None
    assert failed.error.type.endswith("no-target-objects")
    assert failed.target_detections == ()  # recorded with the failure
    assert failed.iterations == ()


def test_plots_events_listing_and_scenes(stack):
    image = render(stack, "demo", 6, 12)
    final = run_search(stack, image, "demo", seed=5)
    with httpx.Client(base_url=stack.controller, timeout=30, headers=auth(stack)) as http:
        for name in ("trajectory.png", "distance.png"):
            response = http.get(f"/searches/{final.id}/{name}")
            assert response.status_code == 200
            assert response.headers["content-type"] == "image/png"
            assert (
                cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
                is not None
            )
        events = http.get(f"/searches/{final.id}/events").text
        assert events.count("event: iteration") == len(final.iterations)
        assert events.count("event: end") == 1
        page = http.get("/searches", params={"limit": 2}).json()
        assert page["total"] >= 1
        assert page["items"][0]["id"] == final.id  # newest first
        assert {s["id"] for s in http.get("/scenes").json()} >= {"demo", "garden"}
        answer = http.get("/health")
        health = answer.json()
        assert all(r["up"] for r in health["replicas"])
        names = [r["name"] for r in health["replicas"]]
        assert names == ["renderer-1", "detector-1", "optimizer-1"]
        assert "127.0.0.1" not in answer.text  # addresses are for the log only


def test_the_stages_serve_the_stacks_token_only_and_every_service_is_ready(stack):
    """The searches above went through the controller, which sends the token; a stranger gets
    401 from every stage, and every service says it is alive and ready."""
    stranger = {"Authorization": "Bearer a-token-that-is-not-the-stacks"}
    for url, method, path in [
        (stack.renderers[0], "GET", "/scenes"),
        (stack.renderers[0], "POST", "/render"),
        (stack.detectors[0], "POST", "/detect"),
        (stack.optimizers[0], "POST", "/next-pose"),
    ]:
        for headers in ({}, stranger):
            response = httpx.request(method, f"{url}{path}", headers=headers, json={}, timeout=30)
            assert response.status_code == 401, (url, path, response.text)
            assert response.headers["content-type"] == "application/problem+json"
        mine = httpx.request(
            method, f"{url}{path}", headers=bearer(stack.service_token), json={}, timeout=30
        )
        assert mine.status_code in {200, 415, 422}, (url, path, mine.text)  # past the token
    for url in (stack.controller, *stack.renderers, *stack.detectors, *stack.optimizers):
        for probe in ("/livez", "/readyz"):
            response = httpx.get(f"{url}{probe}", timeout=30)
            assert response.status_code == 200, (url, probe, response.text)
            assert response.json()["status"] == "ok"


def test_a_search_can_be_cancelled(stack):
    image = render(stack, "demo", 10, 0)
    with controller_client(stack) as client:
        search = client.submit(
            image,
            "demo",
            strategy="simple",
            start_theta_deg=7.5,
            start_phi_deg=180,
            max_iterations=200,
        )
        cancelled = httpx.delete(
            f"{stack.controller}/searches/{search.id}", headers=auth(stack)
        ).json()
        assert cancelled["status"] == "cancelled"
        time.sleep(1.0)
        assert client.get(search.id).status == "cancelled"


def png_bytes() -> bytes:
    ok, buffer = cv2.imencode(".png", np.zeros((24, 32, 3), np.uint8))
    assert ok
    return bytes(buffer)


@pytest.mark.parametrize("how", ["form", "raw"])
@pytest.mark.parametrize(
    ("image", "data", "status", "field"),
    [
        ((b"not an image", "image/png"), {"scene": "demo"}, 415, None),
        ((b"\x89PNG\r\n\x1a\n" + b"\0" * 10, "image/png"), {"scene": "demo"}, 422, None),
        ((b"", "image/png"), {"scene": "demo"}, 422, None),
        ("png", {"scene": "nope"}, 404, "scene"),
        ("png", {"scene": "../etc"}, 404, "scene"),
        ("png", {}, 422, "scene"),
        ("png", {"scene": ""}, 422, "scene"),
        ("png", {"scene": "demo", "strategy": "guess"}, 422, "strategy"),
        (
            "png",
            {"scene": "demo", "start_theta_deg": "100", "start_phi_deg": "0"},
            422,
            "start_theta_deg",
        ),
        ("png", {"scene": "demo", "start_theta_deg": "nan", "start_phi_deg": "0"}, 422, None),
        ("png", {"scene": "demo", "start_theta_deg": "10"}, 422, "start_theta_deg"),
        ("png", {"scene": "demo", "max_iterations": "0"}, 422, "max_iterations"),
        ("png", {"scene": "demo", "max_iterations": "many"}, 422, "max_iterations"),
        ("png", {"scene": "demo", "seed": "-1"}, 422, "seed"),
    ],
)
def test_bad_submissions_get_problem_details(stack, how, image, data, status, field):
    """Each bad submission as a form (options as fields) and as a raw body (options in the
    query): the same status and field either way."""
    content, media_type = (png_bytes(), "image/png") if image == "png" else image
    url = f"{stack.controller}/searches"
    if how == "form":
        files = {"image": ("t", content, media_type)}
        response = httpx.post(url, files=files, data=data, timeout=30, headers=auth(stack))
    else:
        headers = {"Content-Type": media_type, **auth(stack)}
        response = httpx.post(url, content=content, params=data, headers=headers, timeout=30)
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    if field is not None:
        assert response.json().get("field") == field, response.json()


PNG_BODY = {"headers": {"Content-Type": "image/png"}}


@pytest.mark.parametrize(
    ("request_args", "status", "field"),
    [
        pytest.param({"data": {"scene": "demo"}}, 415, "content-type", id="urlencoded"),
        pytest.param(
            {"files": {"other": ("t", b"x", "image/png")}, "data": {"scene": "demo"}},
            422,
            "image",
            id="no-file",
        ),
        pytest.param(
            {"files": {"x": ("t", b"x")}, "data": {"scene": "demo", "image": "text"}},
            422,
            "image",
            id="image-as-text",
        ),
        pytest.param(
            {"content": b"x", "headers": {"Content-Type": "text/plain"}, "params": "scene=demo"},
            415,
            "content-type",
            id="text-body",
        ),
        pytest.param(
            {
                "files": {"image": ("t", b"x", "image/png")},
                "data": {"scene": "demo"},
                "params": "scene=demo",
            },
            422,
            "scene",
            id="form-and-query",
        ),
        pytest.param(
            {"content": b"x", **PNG_BODY, "params": "scene=demo&seed=1&seed=2"},
            422,
            "seed",
            id="query-twice",
        ),
        pytest.param(
            {"content": b"--x\r\n", "headers": {"Content-Type": "multipart/form-data"}},
            400,
            "body",
            id="broken-form",
        ),
    ],
)
def test_bad_submission_shapes_get_problem_details(stack, request_args, status, field):
    request_args = {**request_args, "headers": {**request_args.get("headers", {}), **auth(stack)}}
    response = httpx.post(f"{stack.controller}/searches", timeout=30, **request_args)
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    assert response.json().get("field") == field, response.json()


def test_a_raw_submission_searches_like_a_form(stack):
    """The image as the body and the options in the query start the same search a form does."""
    image = render(stack, "demo", 4, 12)
    options = {"scene": "demo", "strategy": "reprojection", "seed": "5", "max_iterations": "10"}
    raw = httpx.post(
        f"{stack.controller}/searches",
        content=image,
        params=options,
        headers={"Content-Type": "image/png", **auth(stack)},
        timeout=30,
    )
    form = httpx.post(
        f"{stack.controller}/searches",
        files={"image": ("t.png", image, "image/png")},
        data=options,
        timeout=30,
        headers=auth(stack),
    )
    assert raw.status_code == form.status_code == 202, (raw.text, form.text)
    with controller_client(stack) as client:
        found = []
        for answer in (raw, form):
            *_, end = client.follow(answer.json()["id"])
            assert isinstance(end, Search)
            found.append(end)
    assert found[0].start == found[1].start  # the same seed, the same start
    assert found[0].status == found[1].status == "succeeded"
    results = [s.result for s in found]
    assert None not in results
    assert results[0] == results[1]


def test_unknown_searches_and_oversized_uploads_and_no_key(stack):
    response = httpx.get(f"{stack.controller}/searches", timeout=30)
    assert response.status_code == 401
    assert response.headers["www-authenticate"].startswith("Bearer")
    with httpx.Client(base_url=stack.controller, timeout=30, headers=auth(stack)) as http:
        for method, path in [
            ("GET", "/searches/nope"),
            ("DELETE", "/searches/nope"),
            ("GET", "/searches/nope/events"),
            ("GET", "/searches/nope/trajectory.png"),
        ]:
            response = http.request(method, path)
            assert response.status_code == 404
            assert response.headers["content-type"] == "application/problem+json"
        limit = ControllerSettings.model_fields["controller_max_upload_bytes"].default
        huge = {"image": ("t.png", b"\x89PNG" + b"\0" * (limit + 1024 * 1024), "image/png")}
        response = http.post("/searches", files=huge, data={"scene": "demo"})
        assert response.status_code == 413


def test_a_killed_controller_resumes_its_searches(tmp_path):
    """SIGKILL the controller mid-search; a new one on the same database finishes the search
    from its last recorded iteration."""
    ports = [free_port() for _ in range(4)]
    database_url = f"sqlite:///{tmp_path}/controller.sqlite3"
    plan = plan_stack(
        controller_port=ports[0],
        renderer_port=ports[1],
        detector_port=ports[2],
        optimizer_port=ports[3],
        database_url=database_url,
    )
    key = local_key(database_url)
    with running_stack(plan, tmp_path / "logs", api_key=key) as stack:
        image = render(stack, "demo", 9, 30)
        with controller_client(stack) as client:
            search = client.submit(
                image,
                "demo",
                strategy="simple",
                start_theta_deg=7.5,
                start_phi_deg=0,
                max_iterations=80,
            )
            deadline = time.monotonic() + 120
            while len(client.get(search.id).iterations) < 3:
                assert time.monotonic() < deadline, "the search made no progress"
                time.sleep(0.05)
        controller = stack.processes[-1]
        os.kill(controller.process.pid, signal.SIGKILL)
        controller.process.wait(timeout=10)
        (spec,) = [p for p in plan if p.name == "controller"]
        again = spawn_service(spec.app, tmp_path / "logs2", port=spec.port, env=spec.env)
        try:
            wait_healthy(again)
            with ControllerClient(again.url, api_key=key) as client:
                seen = client.get(search.id)
                assert seen.status in {"queued", "running", "succeeded"}
                recorded = len(seen.iterations)
                deadline = time.monotonic() + 180
                while client.get(search.id).status in {"queued", "running"}:
                    assert time.monotonic() < deadline, "the resumed search did not finish"
                    time.sleep(0.1)
                final = client.get(search.id)
        finally:
            stop_service(again)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed, final.result
    assert final.result.pose.index.lat == 9
    assert final.result.pose.index.lon == 30
    indices = [i.index for i in final.iterations]
    assert indices == list(range(len(indices)))
    assert len(indices) > recorded >= 3


def test_searches_ride_out_a_detector_outage_or_resume_when_retried(tmp_path):
    """The only detector stops. Back within the outage budget (10 s here), the running search
    succeeds; gone for longer, the search fails saying so, and once the detector is back, POST
    /searches/{id}/retry resumes it from its recorded iterations and it succeeds."""
    ports = [free_port() for _ in range(4)]
    database_url = f"sqlite:///{tmp_path}/controller.sqlite3"
    plan = plan_stack(
        controller_port=ports[0],
        renderer_port=ports[1],
        detector_port=ports[2],
        optimizer_port=ports[3],
        database_url=database_url,
        env={"COSMOS_CONTROLLER_OUTAGE_BUDGET_S": "10"},
    )
    (detector_plan,) = [p for p in plan if p.name == "detector"]
    with running_stack(plan, tmp_path / "logs", api_key=local_key(database_url)) as stack:
        (detector,) = [p for p in stack.processes if p.url == stack.detectors[0]]
        image = render(stack, "demo", 9, 30)
        http = httpx.Client(base_url=stack.controller, timeout=30, headers=auth(stack))

        def start_far_away() -> str:
            response = http.post(
                "/searches",
                content=image,
                headers={"Content-Type": "image/png"},
                params={
                    "scene": "demo",
                    "strategy": "simple",
                    "start_theta_deg": "7.5",
                    "start_phi_deg": "0",
                    "max_iterations": "80",
                },
            )
            assert response.status_code == 202, response.text
            search_id: str = response.json()["id"]
            wait_for(lambda: len(http.get(f"/searches/{search_id}").json()["iterations"]) >= 2)
            return search_id

        def finished(search_id: str) -> dict:
            wait_for(
                lambda: http.get(f"/searches/{search_id}").json()["status"] not in UNFINISHED,
                timeout_s=180,
            )
            found: dict = http.get(f"/searches/{search_id}").json()
            return found

        def restart_detector() -> None:
            again = spawn_service(
                detector_plan.app,
                tmp_path / "logs-again",
                port=detector_plan.port,
                env=detector_plan.env,  # with the stack's service token
            )
            wait_healthy(again)
            restarted.append(again)

        restarted: list = []
        try:
            # back within the budget: the running search waits and succeeds
            short = start_far_away()
            stop_service(detector)
            wait_for(lambda: http.get("/health").json()["unavailable_stages"] == ["detector"])
            refused = http.post(
                "/searches",
                content=image,
                params={"scene": "demo"},
                headers={"Content-Type": "image/png"},
            )
            assert refused.status_code == 503, refused.text
            assert refused.headers["retry-after"] == "5"
            time.sleep(1.0)
            restart_detector()
            search = finished(short)
            assert search["status"] == "succeeded", search["error"]
            assert search["result"]["pose"]["index"] == {"lat": 9, "lon": 30}

            # gone for longer: the search fails saying so; retried once it is back, it resumes
            long = start_far_away()
            stop_service(restarted.pop())
            failed = finished(long)
            assert failed["status"] == "failed"
            assert failed["error"]["type"] == "urn:cosmos:problem:stage-unavailable"
            assert "the detector was unavailable" in failed["error"]["detail"]
            assert f"POST /searches/{long}/retry" in failed["error"]["detail"]
            assert "127.0.0.1" not in failed["error"]["detail"]
            assert http.post(f"/searches/{long}/retry").status_code == 503  # still down
            restart_detector()
            wait_for(lambda: http.get("/health").json()["status"] == "ok")
            retried = http.post(f"/searches/{long}/retry")
            assert retried.status_code == 202, retried.text
            search = finished(long)
            assert search["status"] == "succeeded", search["error"]
            assert search["result"]["pose"]["index"] == {"lat": 9, "lon": 30}
            recorded = failed["iterations"]
            assert search["iterations"][: len(recorded)] == recorded  # resumed, not redone
            indices = [it["index"] for it in search["iterations"]]
            assert indices == list(range(len(indices)))
        finally:
            http.close()
            for process in restarted:
                stop_service(process)


UNFINISHED = {"queued", "running"}


def wait_for(check, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.1)


def test_every_controller_route_answers_within_its_schema(stack):
    """Schema-driven fuzzing of the public API (see :func:`tests.support.fuzz_service`)."""
    assert fuzz_service(stack.controller, max_examples=15, headers=auth(stack)) >= 8


def test_a_killed_renderer_is_started_again_while_the_other_serves(tmp_path):
    """``cosmos up``'s supervision: SIGKILL one renderer of two; a search submitted right then
    succeeds on the other, the controller stays ready, and the killed one is started again on
    its port (with the stack's token) and answers again."""
    said: list[str] = []
    plan = plan_local_stack(tmp_path, renderers=2)
    key = local_key(plan[-1].env["COSMOS_CONTROLLER_DATABASE_URL"])
    logs = tmp_path / "logs"
    with running_stack(plan, logs, api_key=key, supervise=True, say=said.append) as stack:
        assert stack.supervisor is not None
        image = render(stack, "demo", 5, 14)
        victim = next(p for p in stack.processes if p.url == stack.renderers[1])
        os.kill(victim.process.pid, signal.SIGKILL)
        victim.process.wait(timeout=10)
        final = run_search(stack, image, "demo", seed=11)
        assert final.status == "succeeded", final.error
        assert final.result is not None
        assert (final.result.pose.index.lat, final.result.pose.index.lon) == (5, 14)
        assert httpx.get(f"{stack.controller}/readyz", timeout=30).status_code == 200  # no key
        deadline = time.monotonic() + 120
        while True:
            assert time.monotonic() < deadline, f"the renderer did not come back: {said}"
            try:
                if httpx.get(f"{victim.url}/livez", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        assert stack.supervisor.restarts(victim.url) == 1
        (again,) = [p for p in stack.supervisor.processes if p.url == victim.url]
        assert again.process.pid != victim.process.pid
        assert any(f"{victim.url} exited (signal 9)" in line for line in said), said
        assert any(f"{victim.url} started again (restart 1" in line for line in said), said
        with RendererClient(victim.url, token=stack.service_token) as client:
            assert {s.id for s in client.scenes()} >= {"demo"}
        final = run_search(stack, image, "demo", seed=12)  # both renderers serve again
        assert final.status == "succeeded", final.error
    assert all(p.process.poll() is not None for p in stack.supervisor.processes)
