"""The controller service: ``create_app(settings)`` builds it; ``app`` is the default instance.

Run it with ``uvicorn services.controller.app:app --port 8000``.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware
from starlette.types import Scope

from services.common.errors import StartupError
from services.common.http import service_app
from services.common.settings import from_environment
from services.controller.api import router
from services.controller.auth import ApiKeyMiddleware, needs_key
from services.controller.keys import KeyStore
from services.controller.readiness import ControllerReadiness
from services.controller.settings import ControllerSettings
from services.controller.store import DatabaseUnavailable
from services.controller.transport import Transport
from services.controller.wiring import Controller, build_controller

__all__ = ["app", "create_app"]


def _keys_of(scope: Scope) -> KeyStore:
    """The API keys of the controller app serving ``scope`` (built by its lifespan)."""
    controller: Controller = scope["app"].state.controller
    return controller.keys


def create_app(
    settings: ControllerSettings | None = None, *, transport: Transport | None = None
) -> FastAPI:
    """A controller app; reads ``COSMOS_*`` settings from the environment unless given
    (and then warns of each ``COSMOS_`` variable that no service reads).

    ``transport`` carries the calls to the stages (HTTP/1.1 over the network unless given; tests
    hand requests to in-process apps), each with the service token.
    """
    settings = settings or from_environment(ControllerSettings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            controller = await build_controller(settings, transport=transport)
        except DatabaseUnavailable as exc:
            raise StartupError(str(exc)) from None
        except ValueError as exc:  # a database URL of neither kind
            raise StartupError(str(exc)) from None
        await controller.start()
        app.state.controller = controller
        app.state.readiness = controller.readiness
        try:
            yield
        finally:
            await controller.close()

    async def readiness(app: FastAPI) -> list[str]:
        check: ControllerReadiness = app.state.readiness
        return await check.unready()

    app = service_app(
        "controller",
        "Runs searches for where a camera stood, over the renderer, detector, optimizer.",
        lifespan,
        router,
        settings.body_limits(),
        settings=settings,
        guarded=False,  # its public API takes API keys (api.py); it sends the stages the token
        readiness=readiness,
    )
    if settings.controller_auth:
        # Added after the body bounds, so it runs before them: a request with a body and no
        # valid key is refused before its body is admitted or read (auth.py).
        app.add_middleware(
            ApiKeyMiddleware, needs_key=partial(needs_key, router.routes), keys=_keys_of
        )
    origins = settings.cors_origins()
    if origins:  # none: no CORS headers, so browsers keep other origins' pages out
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "X-Request-ID"],
            expose_headers=["Location", "Retry-After", "WWW-Authenticate"],
            max_age=600,
        )
    return app


app = create_app()
