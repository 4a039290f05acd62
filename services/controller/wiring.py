"""The controller's composition root: :func:`build_controller` builds its parts once, for the
app's lifespan, the benchmarks and the tests alike; :class:`Controller` starts and stops them."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import secrets
import socket
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta

from services.controller.broker import Broker
from services.controller.discovery import expand_urls
from services.controller.events import Notifier
from services.controller.keys import KeyStore
from services.controller.plots import PlotCache
from services.controller.quotas import Limits, Quotas
from services.controller.readiness import ControllerReadiness
from services.controller.runner import SearchRunner
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages
from services.controller.store import (
    Leases,
    PostgresDatabase,
    SearchStore,
    open_database,
    utcnow,
)
from services.controller.store.changes import ChangeListener
from services.controller.submit import Admission
from services.controller.transport import AiohttpTransport, Transport, WithServiceToken
from services.controller.views import ViewStore

__all__ = ["Controller", "build_controller"]

_log = logging.getLogger("cosmos.controller")


async def _discover(broker: Broker, settings: ControllerSettings) -> None:
    """Keep each stage's replicas in step with what its host names resolve to."""
    while True:
        for stage, urls in settings.pools().items():
            await broker.set_pool(stage, await expand_urls(urls))
        await asyncio.sleep(settings.controller_discovery_interval_s)


def _waking(notifier: Notifier) -> Callable[[str | None], None]:
    """What the change listener calls from its thread: wakes the followers of the search that
    changed (None: of every search) on this event loop."""
    loop = asyncio.get_running_loop()

    def changed(search_id: str | None) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody follows any more
            if search_id is None:
                loop.call_soon_threadsafe(notifier.publish_all)
            else:
                loop.call_soon_threadsafe(notifier.publish, search_id)

    return changed


def _holder() -> str:
    """This controller's name in the leases it holds: host, process, and a random part (a
    restarted process with a reused id is another holder)."""
    return f"{socket.gethostname()}:{os.getpid()}:{secrets.token_hex(3)}"


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


@dataclass
class Controller:
    """The controller's parts, built by :func:`build_controller`; the routes reach them as the
    app's state."""

    settings: ControllerSettings
    store: SearchStore
    broker: Broker
    stages: Stages
    runner: SearchRunner
    notifier: Notifier
    keys: KeyStore
    quotas: Quotas
    views: ViewStore
    admission: Admission
    readiness: ControllerReadiness
    plots: PlotCache = field(default_factory=PlotCache)
    _tasks: list[asyncio.Task[None]] = field(default_factory=list, repr=False)
    _listener: ChangeListener | None = field(default=None, repr=False)

    async def start(self) -> None:
        """Probe the stages, discover their replicas (when set to), run the queued searches and
        expire the old ones."""
        await self.broker.start()
        if self.settings.controller_discover_replicas:
            self._tasks.append(asyncio.create_task(_discover(self.broker, self.settings)))
        await self.runner.start()
        self._tasks.append(asyncio.create_task(_expire(self.store, self.settings)))
        database = self.store.database
        if isinstance(database, PostgresDatabase):  # searches other controllers run, followed
            self._listener = database.listen(_waking(self.notifier))

    async def close(self) -> None:
        """Stop all that :meth:`start` started (running searches resume on the next start) and
        close the stores."""
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._listener is not None:
            await asyncio.to_thread(self._listener.close)
        await self.runner.close()
        await self.broker.close()
        self.keys.close()
        self.store.close()


async def build_controller(
    settings: ControllerSettings,
    *,
    transport: Transport | None = None,
    stages_class: type[Stages] = Stages,
) -> Controller:
    """The controller's parts, wired once, not started.

    ``transport`` carries the calls to the stages (HTTP/1.1 over the network unless given; tests
    hand requests to in-process apps), each with the service token; ``stages_class`` makes the
    stage calls (a benchmark records them with a subclass).
    """
    database = await asyncio.to_thread(
        open_database,
        settings.controller_database_url,
        # a cut-off controller's connections, and their locks, go before its leases run out
        dead_after_s=settings.controller_lease_s / 2,
    )
    store = SearchStore(database)
    keys = KeyStore(database)
    leases = (
        Leases(database, _holder(), settings.controller_lease_s)
        if database.dialect == "postgresql"
        else None
    )
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
    stages = stages_class(
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
        leases=leases,
    )
    admission = Admission(settings, store, stages, broker, runner, quotas)
    readiness = ControllerReadiness(store, broker, to_stages)
    return Controller(
        settings, store, broker, stages, runner, notifier, keys, quotas, views, admission, readiness
    )
