"""The controller's stage calls against the real renderer and detector apps (in process): views
are fetched as binary PPM and detected as such, a renderer that only answers PNG still works, and
a submission's start view is rendered early and taken by its search once (or dropped); a free
search's refinements go back to the optimizer replica that keeps its target."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from urllib.parse import urlsplit

import cv2
import httpx
import numpy as np
import pytest
from asgi_lifespan import LifespanManager
from starlette.types import ASGIApp, Receive, Scope, Send

from services.common.auth import token_from_environment
from services.common.contracts.free import FreePoseRequest
from services.common.contracts.optimize import ImageDetections
from services.common.contracts.refine import RefinePoseRequest, TargetRequest
from services.common.contracts.search import Search, SearchOptions, ViewSettings
from services.common.errors import UnprocessableError
from services.common.geometry.free_camera import FreeCamera
from services.common.geometry.pose import GridIndex
from services.common.images import PPM_MEDIA_TYPE, decode_image, media_type_of
from services.controller.broker import Broker
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages, request_json
from services.controller.store import SearchStore, open_store
from services.controller.submit import create_search
from services.controller.transport import StageAnswer, StageRequest, WithServiceToken
from services.detector.app import create_app as create_detector
from services.detector.settings import DetectorSettings
from services.optimizer.app import create_app as create_optimizer
from services.renderer.app import create_app as create_renderer
from tests.controller.free_stages import candidate
from tests.scene_model_support import BALLS, add_scene, onboard

pytestmark = pytest.mark.anyio


class PngOnly:
    """A renderer of an older version: ignores the Accept header."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            headers = [(k, v) for k, v in scope["headers"] if k.lower() != b"accept"]
            scope = {**scope, "headers": headers}
        await self.app(scope, receive, send)


@pytest.fixture(scope="module")
async def apps() -> AsyncIterator[tuple[ASGIApp, ASGIApp]]:
    async with (
        LifespanManager(create_renderer()) as renderer,
        LifespanManager(create_detector()) as detector,
    ):
        yield renderer.app, detector.app


class InProcessApps:
    """A transport that hands each request to the in-process app named by the URL's host."""

    def __init__(self, apps: dict[str, ASGIApp]) -> None:
        self.clients = {
            host: httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://app")
            for host, app in apps.items()
        }

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        client = self.clients[urlsplit(base_url).hostname or ""]
        response = await client.request(
            request.method, request.path, content=request.body, headers=dict(request.headers)
        )
        return StageAnswer(response.status_code, response.content, dict(response.headers))

    async def close(self) -> None:
        for client in self.clients.values():
            await client.aclose()


def stages_over(renderer: ASGIApp, detector: ASGIApp) -> Stages:
    apps = InProcessApps({"renderer": renderer, "detector": detector})
    broker = Broker(
        {"renderer": ["http://renderer"], "detector": ["http://detector"]},
        transport=WithServiceToken(apps, token_from_environment()),  # the app's, as it sends
        health_interval_s=0,
    )
    return Stages(broker, render_spp=2)


@pytest.mark.parametrize("old_renderer", [False, True], ids=["ppm", "png-only renderer"])
async def test_a_view_is_rendered_and_detected(apps, old_renderer):
    renderer, detector = apps
    stages = stages_over(PngOnly(renderer) if old_renderer else renderer, detector)
    try:
        view = await stages.render("demo", GridIndex(lat=3, lon=5))
        media_type = media_type_of(view)
        assert media_type == ("image/png" if old_renderer else PPM_MEDIA_TYPE)
        found = await stages.detect(view, media_type)
        assert found.image_size == (320, 240)
        assert len(found.detections) >= 3  # the demo's balls seen from an upper ring
    finally:
        await stages.broker.close()


class Counting:
    """An app that counts the requests it serves (their paths and query strings)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.requests: list[str] = []
        self.queries: list[str] = []

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            self.requests.append(scope["path"])
            self.queries.append(scope["query_string"].decode())
        await self.app(scope, receive, send)


async def test_a_detection_names_the_search_scene_so_its_own_model_answers(apps, tmp_path):
    """The scene travels as ``?scene=``; a scene with its own model (``field``, the demo with its
    balls as classes) is detected with it, one without (``plain``, another copy) with the
    general model."""
    renderer, _ = apps
    add_scene(tmp_path, "field")
    onboard(tmp_path, "field")
    add_scene(tmp_path, "plain")
    settings = DetectorSettings(scenes_dir=str(tmp_path), detector_threads=1)
    async with LifespanManager(create_detector(settings)) as detector:
        counting = Counting(detector.app)
        stages = stages_over(renderer, counting)
        try:
            view = await stages.render("demo", GridIndex(lat=3, lon=5))
            own = await stages.detect(view, media_type_of(view), "search-1", scene="field")
            general = await stages.detect(view, media_type_of(view), "search-1", scene="plain")
        finally:
            await stages.broker.close()
    assert counting.queries == ["scene=field", "scene=plain"]
    assert own.model.scene == "field"
    assert {d.label for d in own.detections} <= set(BALLS)
    assert len(own.detections) >= 3
    assert general.model.scene is None
    assert {d.label for d in general.detections} == {"sphere"}


async def test_an_early_render_is_taken_by_its_search_once(apps):
    renderer, detector = apps
    counting = Counting(renderer)
    stages = stages_over(counting, detector)
    start = GridIndex(lat=3, lon=5)
    try:
        stages.render_early("demo", start, "search-1")
        stages.render_early("demo", start, "search-1")  # already under way: not asked twice
        early = await stages.render("demo", start, "search-1")
        assert counting.requests == ["/render"]
        assert early == await stages.render("demo", start, "search-1")  # a new render: seed 0
        assert counting.requests == ["/render", "/render"]
        stages.render_early("demo", start, "search-2")
        other = await stages.render("demo", start, "search-3")  # not search-2's
        assert other == early
        stages.forget_early("search-2")
        assert stages._early == {}
    finally:
        await stages.broker.close()


def shape_of(image: bytes) -> tuple[int, ...]:
    return decode_image(image, max_pixels=1 << 20, max_side=4096).shape


async def test_a_view_is_rendered_with_a_search_s_settings_else_the_current_ones(apps):
    """A search's own settings (here a smaller film, 1 spp) go to the renderer and to the view
    store's hook; none means the controller's current ones (2 spp, the scene's 320 px). An early
    render is taken only by a render with its settings."""
    renderer, detector = apps
    counting = Counting(renderer)
    stages = stages_over(counting, detector)
    told: list[tuple[ViewSettings, tuple[int, ...]]] = []
    stages.on_render = lambda scene, index, settings, image: told.append(
        (settings, shape_of(image))
    )
    start = GridIndex(lat=3, lon=5)
    small = ViewSettings(spp=1, width=160)
    try:
        stages.render_early("demo", start, "search-1", small)
        current = await stages.render("demo", start, "search-1")  # not with the early settings
        assert counting.requests == ["/render", "/render"]
        own = await stages.render("demo", start, "search-1", small)  # the early one
        assert counting.requests == ["/render", "/render"]
        assert shape_of(current) == (240, 320, 3)
        assert shape_of(own) == (120, 160, 3)
        assert sorted(told, key=lambda t: t[1]) == [
            (small, (120, 160, 3)),
            (ViewSettings(spp=2), (240, 320, 3)),
        ]
        assert stages.settings_for(None) == ViewSettings(spp=2)
        assert stages.settings_for(small) is small
    finally:
        await stages.broker.close()


async def test_a_failed_early_render_nobody_took_is_not_reported(apps):
    """A failure of a dropped early render is retrieved when it is dropped: asyncio would
    otherwise log 'Task exception was never retrieved' when the task is collected."""
    renderer, detector = apps
    stages = stages_over(renderer, detector)
    try:
        stages.render_early("no-such-scene", GridIndex(lat=0, lon=0), "search-1")
        (task,) = stages._early.values()
        await asyncio.wait([task])  # failed (an unknown scene); nothing retrieved it yet
        assert task._log_traceback  # what makes asyncio report it when collected
        stages.forget_early("search-1")
        await asyncio.sleep(0)  # the done callback runs
        assert not task._log_traceback
        assert stages._early == {}
    finally:
        await stages.broker.close()


def _png(width: int = 64, height: int = 48) -> bytes:
    rgb = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    ok, buffer = cv2.imencode(".png", rgb)
    assert ok
    return buffer.tobytes()


async def _submit(stages: Stages, store: SearchStore, image: bytes) -> Search:
    options = SearchOptions(
        scene="demo", start_theta_deg=45.0, start_phi_deg=30.0, seed=1, max_iterations=10
    )
    limits = ControllerSettings(
        controller_max_image_pixels=1_000_000, controller_max_image_side=4096
    )
    return await create_search(store, stages, image, options, limits, start_early=True)


async def test_a_submission_starts_its_start_view_before_it_is_stored(apps):
    renderer, detector = apps
    counting = Counting(renderer)
    stages = stages_over(counting, detector)
    store = open_store("sqlite:///:memory:")
    try:
        search = await _submit(stages, store, _png())
        assert store.get(search.id) is not None
        assert search.target_size == (64, 48)
        assert search.view_settings == stages.view_settings == ViewSettings(spp=2)
        assert list(stages._early) == [
            (search.id, "demo", *search.start.index.model_dump().values(), search.view_settings)
        ]
        view = await stages.render("demo", search.start.index, search.id)  # the early one
        assert media_type_of(view) == PPM_MEDIA_TYPE
        assert counting.requests.count("/render") == 1
    finally:
        store.close()
        await stages.broker.close()


async def test_a_broken_image_drops_its_early_render_and_records_nothing(apps):
    renderer, detector = apps
    stages = stages_over(renderer, detector)
    store = open_store("sqlite:///:memory:")
    png = _png()
    try:
        with pytest.raises(UnprocessableError) as refused:  # the header is fine, the data not
            await _submit(stages, store, png[: len(png) // 2])
        assert refused.value.slug == "invalid-image"
        assert stages._early == {}
        assert store.page(10, 0) == ([], 0)
    finally:
        store.close()
        await stages.broker.close()


def test_a_refinement_of_an_alternative_pose_is_sent_whole():
    """An alternative from /free-pose has no σ (null): the body keeps the field, so the
    optimizer reads back the very request (it was refused as missing once)."""
    pose = candidate(1.0).model_copy(update={"position_sigma": None, "rotation_sigma_deg": None})
    request = RefinePoseRequest(scene="demo", pose=pose, fit_focal=True)
    assert RefinePoseRequest.model_validate_json(request_json(request)) == request


async def test_a_search_s_refinements_return_to_the_optimizer_that_keeps_its_target(apps):
    """Two optimizer replicas: the target made ready on one, every refinement of the search
    goes back to it (its maps found kept there), though the broker would take turns; the
    other replica keeps nothing."""
    renderer, detector = apps
    async with (
        LifespanManager(create_optimizer()) as first,
        LifespanManager(create_optimizer()) as second,
    ):
        optimizers = {"optimizer-a": first.app, "optimizer-b": second.app}
        transport = InProcessApps({"renderer": renderer, "detector": detector, **optimizers})
        broker = Broker(
            {
                "renderer": ["http://renderer"],
                "detector": ["http://detector"],
                "optimizer": [f"http://{host}" for host in optimizers],
            },
            transport=WithServiceToken(transport, token_from_environment()),
            health_interval_s=0,
        )
        stages = Stages(broker, render_spp=4)
        try:
            truth = FreeCamera(position=(4.0, 5.0, 6.0), look_at=(-0.2, 0.4, 0.0), fov_deg=50.0)
            photo = await stages.render_camera("demo", truth, (320, 240))
            found = await stages.detect(photo, media_type_of(photo))
            target = ImageDetections(image_size=found.image_size, detections=found.detections)
            answer = await stages.free_pose(FreePoseRequest(scene="demo", target=target))
            assert answer.pose is not None
            archive = await stages.render_camera(
                "demo", answer.pose.camera(), (320, 240), with_depth=True
            )
            await stages.prepare_target(TargetRequest(film=(320, 240)), photo, "s1")
            request = RefinePoseRequest(scene="demo", pose=answer.pose)
            for _ in range(3):
                refined = await stages.refine_pose(request, photo, archive, "s1")
                assert refined.fit.converged
            kept = [
                (await transport.clients[host].get("/health")).json()["target_cache"]
                for host in optimizers
            ]
            assert sorted((c["misses"], c["hits"], c["targets"]) for c in kept) == [
                (0, 0, 0),
                (1, 3, 1),
            ]
        finally:
            await broker.close()
