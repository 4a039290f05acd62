"""The controller's fixtures: an in-process controller whose renderer knows two scenes, and
clients that carry an API key."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
from asgi_lifespan import LifespanManager
from fastapi import FastAPI
from starlette.types import ASGIApp

from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.contracts.render import SceneDetail
from services.controller.app import create_app as create_controller
from services.controller.settings import ControllerSettings
from services.controller.transport import StageAnswer, StageRequest
from services.renderer.app import create_app as create_renderer
from services.renderer.settings import RendererSettings
from tests.controller.clients import key_client, new_key


class RendererOnly:
    """A transport that hands renderer calls to an in-process app; other stages are down."""

    def __init__(self, renderer: ASGIApp) -> None:
        self.client = httpx.AsyncClient(
            transport=httpx.ASGITransport(app=renderer), base_url="http://renderer"
        )

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        if urlsplit(base_url).hostname != "renderer":
            return StageAnswer(503, b"", {})
        response = await self.client.request(
            request.method, request.path, content=request.body, headers=dict(request.headers)
        )
        return StageAnswer(response.status_code, response.content, dict(response.headers))

    async def close(self) -> None:
        await self.client.aclose()


Controller = tuple[FastAPI, httpx.AsyncClient]
StartController = Callable[..., AbstractAsyncContextManager[Controller]]


@pytest.fixture
def detail(catalog) -> SceneDetail:
    """The demo scene as the renderer describes it."""
    scene = catalog.get("demo")
    return SceneDetail(id="demo", spec=scene.spec, grid=scene.spec.search)


@pytest.fixture
def start_controller(tmp_path: Path) -> StartController:
    """Starts a controller whose renderer knows ``demo`` and ``fine`` (the demo scene at a 0.5°
    step, which the scene format allows and the optimizer does not search), with ``settings``
    changed as given; yields the app and a client with a tenant's key (named ``tenant``)."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    demo = (BUILTIN_SCENES_DIR / "demo.yaml").read_text()
    fine = demo.replace("angle_step_deg: 7.5", "angle_step_deg: 0.5")
    assert fine != demo
    (scenes / "fine.yaml").write_text(fine)

    @asynccontextmanager
    async def start(**settings: Any) -> AsyncIterator[Controller]:
        chosen = ControllerSettings(
            controller_renderer_urls="http://renderer",
            controller_detector_urls="http://detector",
            controller_optimizer_urls="http://optimizer",
            **{
                "controller_database_url": f"sqlite:///{tmp_path / 'controller.sqlite3'}",
                **settings,
            },
        )
        renderer = create_renderer(RendererSettings(scenes_dir=str(scenes)))
        async with LifespanManager(renderer) as r:
            app = create_controller(chosen, transport=RendererOnly(r.app))
            async with LifespanManager(app) as c:
                async with key_client(c.app, new_key(app, "tenant")) as client:
                    yield app, client

    return start


@pytest.fixture
async def controller(start_controller: StartController) -> AsyncIterator[Controller]:
    """A controller with the default settings (see :func:`start_controller`)."""
    async with start_controller() as running:
        yield running
