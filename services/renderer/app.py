"""The renderer service: ``create_app(settings)`` builds it; ``app`` is the default instance.

Run it with ``python -m services.common.server services.renderer.app:app --port 8001`` (uvicorn
with a request head limit and deadline).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from services.common.http import service_app
from services.common.settings import from_environment
from services.renderer.api import RendererState, router
from services.renderer.settings import RendererSettings
from services.renderer.wiring import build_renderer

__all__ = ["app", "create_app"]


def create_app(settings: RendererSettings | None = None) -> FastAPI:
    """A renderer app; reads ``COSMOS_*`` settings from the environment unless given
    (and then warns of each ``COSMOS_`` variable that no service reads)."""
    settings = settings or from_environment(RendererSettings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = await asyncio.to_thread(build_renderer, settings)
        await asyncio.to_thread(state.engine.start)
        app.state.renderer = state
        try:
            yield
        finally:
            await asyncio.to_thread(state.engine.close)

    async def readiness(app: FastAPI) -> list[str]:
        state: RendererState = app.state.renderer
        return state.unready()

    return service_app(
        "renderer",
        "Renders views of known scenes with Mitsuba 3, with exact ground truth.",
        lifespan,
        router,
        settings.renderer_max_body_bytes,
        settings=settings,
        guarded=True,
        readiness=readiness,
    )


app = create_app()
