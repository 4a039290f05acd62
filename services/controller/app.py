"""The controller service: ``create_app(settings)`` builds it; ``app`` is the default instance.

Run it with ``uvicorn services.controller.app:app --port 8000``.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import timedelta

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware
from starlette.types import Scope

from services.common.http import service_app
from services.common.settings import from_environment
from services.controller.api import ControllerState, needs_key, router
from services.controller.auth import ApiKeyMiddleware
from services.controller.broker import Broker
from services.controller.discovery import expand_urls
from services.controller.events import Notifier
from services.controller.keys import KeyStore
from services.controller.quotas import Limits, Quotas
from services.controller.readiness import ControllerReadiness
from services.controller.runner import SearchRunner
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages
from services.controller.store import SearchStore, utcnow
from services.controller.transport import AiohttpTransport, Transport, WithServiceToken
from services.controller.views import ViewStore

__all__ = ["app", "create_app"]

_log = logging.getLogger("cosmos.controller")


async def _discover(broker: Broker, settings: ControllerSettings) -> None:
    """Keep each stage's replicas in step with what its host names resolve to."""
    while True:
        for stage, urls in settings.pools().items():
            await broker.set_pool(stage, await expand_urls(urls))
        await asyncio.sleep(settings.controller_discovery_interval_s)


async def _expire(store: SearchStore, settings: ControllerSettings) -> None:
    """Delete the searches that finished more than the retention time ago, now and then."""
    retention = timedelta(seconds=settings.controller_retention_s)
    while True:
        try:
            expired = await asyncio.to_thread(store.expire, utcnow() - retention)
        except Exception:  # a failed sweep must not end the sweeping
            _log.exception("expiring old searches failed")
        else:
            if expired:
                _log.info("expired %d searches finished over %s ago", expired, retention)
        await asyncio.sleep(settings.controller_retention_sweep_s)


def _keys_of(scope: Scope) -> KeyStore:
    """The API keys of the controller app serving ``scope`` (built by its lifespan)."""
    state: ControllerState = scope["app"].state.controller
    return state.keys


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
        store = await asyncio.to_thread(SearchStore, settings.controller_database_url)
        keys = await asyncio.to_thread(KeyStore, settings.controller_database_url)
        quotas = Quotas(
            store,
            Limits(
                active_searches=settings.controller_quota_active_searches,
                searches_per_minute=settings.controller_quota_searches_per_minute,
                stored_bytes=settings.controller_quota_stored_bytes,
                retention_s=settings.controller_retention_s,
            ),
        )
        to_stages = WithServiceToken(
            transport or AiohttpTransport(settings.controller_connect_timeout_s), settings.token()
        )
        broker = Broker(
            settings.pools(),
            heuristic=settings.controller_broker_heuristic,
            timeouts_s=settings.timeouts(),
            connect_timeout_s=settings.controller_connect_timeout_s,
            transport=to_stages,
        )
        stages = Stages(
            broker,
            render_spp=settings.controller_view_spp,
            render_width=settings.controller_view_width,
        )
        views = ViewStore(
            lambda scene, index, view: stages.render(scene, index, view_settings=view),
            settings.controller_view_cache_bytes,
        )
        stages.on_render = views.remember  # the page shows the views the searches rendered
        notifier = Notifier()
        runner = SearchRunner(
            store,
            stages,
            notifier,
            settings.controller_max_concurrent_searches,
            outage_budget_s=settings.controller_outage_budget_s,
        )
        await broker.start()
        discovery = (
            asyncio.create_task(_discover(broker, settings))
            if settings.controller_discover_replicas
            else None
        )
        await runner.start()
        expiry = asyncio.create_task(_expire(store, settings))
        app.state.controller = ControllerState(
            settings, store, broker, stages, runner, notifier, keys, quotas, views
        )
        app.state.readiness = ControllerReadiness(store, broker, to_stages)
        try:
            yield
        finally:
            if discovery is not None:
                discovery.cancel()
            expiry.cancel()
            await asyncio.gather(expiry, return_exceptions=True)
            await runner.close()
            await broker.close()
            keys.close()
            store.close()

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
        app.add_middleware(ApiKeyMiddleware, needs_key=needs_key, keys=_keys_of)
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
