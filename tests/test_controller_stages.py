"""The controller's stage calls against the real renderer and detector apps (in process): views
are fetched as binary PPM and detected as such, and a renderer that only answers PNG still works."""

from __future__ import annotations

from collections.abc import AsyncIterator
from urllib.parse import urlsplit

import httpx
import pytest
from asgi_lifespan import LifespanManager
from starlette.types import ASGIApp, Receive, Scope, Send

from services.common.images import PPM_MEDIA_TYPE, media_type_of
from services.common.models import GridIndex
from services.controller.broker import Broker
from services.controller.stages import Stages
from services.controller.transport import StageAnswer, StageRequest
from services.detector.app import create_app as create_detector
from services.renderer.app import create_app as create_renderer

pytestmark = pytest.mark.anyio


@pytest.fixture(scope="module")
def anyio_backend() -> str:
    return "asyncio"


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
    broker = Broker(
        {"renderer": ["http://renderer"], "detector": ["http://detector"]},
        transport=InProcessApps({"renderer": renderer, "detector": detector}),
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
