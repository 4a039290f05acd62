"""The stages as processes and the controller's search loop over them, for benchmarks.

Renderer, detector and optimizer run as uvicorn processes on loopback (:func:`stage_processes`);
:class:`Controller` is the controller's own search loop over them, in this process, without its
HTTP API: a search goes from :func:`~services.controller.submit.create_search` through a
:class:`~services.controller.runner.SearchRunner` to its end, as ``POST /searches`` runs it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from cosmos.bench.target import Target
from cosmos.launch import spawn_service, stop_service, wait_healthy
from services.common.auth import TOKEN_VARIABLE, new_token
from services.common.contracts.optimize import StrategyName
from services.common.contracts.search import TERMINAL_STATUSES
from services.common.geometry.pose import Pose
from services.controller.broker import Broker
from services.controller.events import Notifier
from services.controller.runner import SearchRunner
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages
from services.controller.store import SearchStore
from services.controller.submit import create_search
from services.controller.transport import AiohttpTransport, Transport, WithServiceToken

__all__ = ["SCENE", "Controller", "StageUrls", "stage_processes"]

SCENE = "demo"
STAGES = ("renderer", "detector", "optimizer")
SEARCH_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class StageUrls:
    renderer: str
    detector: str
    optimizer: str
    token: str = field(repr=False)
    """The service token the three stages share."""

    def pools(self) -> dict[str, list[str]]:
        return {
            "renderer": [self.renderer],
            "detector": [self.detector],
            "optimizer": [self.optimizer],
        }


@contextmanager
def stage_processes(workdir: Path) -> Iterator[StageUrls]:
    """Renderer, detector and optimizer as uvicorn processes on free loopback ports, with one
    service token."""
    token = new_token()
    env = {TOKEN_VARIABLE: token}
    started = [spawn_service(f"services.{name}.app:app", workdir, env=env) for name in STAGES]
    try:
        for process in started:
            wait_healthy(process, 120.0)
        renderer, detector, optimizer = (process.url for process in started)
        yield StageUrls(renderer, detector, optimizer, token)
    finally:
        for process in started:
            stop_service(process)


class Controller:
    """The controller's search loop over one transport (the broker's own unless given), with its
    own store and runner; ``stages`` makes its stage calls."""

    def __init__(
        self,
        urls: StageUrls,
        transport: Transport | None,
        database: Path,
        stages: type[Stages] = Stages,
    ) -> None:
        self.settings = ControllerSettings(controller_database_url=f"sqlite:///{database}")
        to_stages = WithServiceToken(transport or AiohttpTransport(2.0), urls.token)
        self.broker = Broker(urls.pools(), transport=to_stages, health_interval_s=0)
        self.stages = stages(self.broker, render_spp=self.settings.controller_view_spp)
        self.store = SearchStore(self.settings.controller_database_url)
        self.notifier = Notifier()
        self.runner = SearchRunner(self.store, self.stages, self.notifier, 1)

    async def start(self) -> None:
        await self.runner.start()

    async def close(self) -> None:
        # A worker cancelled before it has seen its search end takes the cancellation for the
        # search's and carries on (SearchRunner._work), and close() would wait for it forever.
        while self.runner.running:
            await asyncio.sleep(0)
        await self.runner.close()
        await self.broker.close()
        self.store.close()

    async def _ended(self, search_id: str) -> None:
        with self.notifier.following(search_id):
            while True:
                changed = self.notifier.current(search_id)
                state = self.store.status_doc(search_id)
                if state is not None and state[0] in TERMINAL_STATUSES:
                    return
                await changed.wait()

    async def search(
        self, target: Target, strategy: StrategyName, *, start: Pose, seed: int
    ) -> tuple[float, int]:
        """One search for ``target`` from ``start`` as ``POST /searches`` runs it: wall
        milliseconds and stage calls."""
        t0 = time.perf_counter()
        record = await create_search(
            self.store,
            self.stages,
            image=target.image,
            scene_id=target.scene,
            strategy=strategy,
            start_theta_deg=start.theta_deg,
            start_phi_deg=start.phi_deg,
            seed=seed,
            max_iterations=self.settings.controller_default_max_iterations,
            max_image_pixels=self.settings.controller_max_image_pixels,
            max_image_side=self.settings.controller_max_image_side,
            start_early=self.runner.idle,
        )
        self.runner.submit(record.id, recorded=(record, target.image))
        try:
            async with asyncio.timeout(SEARCH_TIMEOUT_S):
                await self._ended(record.id)
        except TimeoutError:
            state = self.store.status_doc(record.id)
            raise RuntimeError(f"search {record.id} still {state and state[0]}") from None
        wall_ms = (time.perf_counter() - t0) * 1000
        search = self.store.get(record.id)
        if search is None or search.status != "succeeded" or search.result is None:
            raise RuntimeError(f"search {record.id} ended {search and search.status}")
        iterations = len(self.store.iterations(record.id))
        renders = search.result.renders
        return wall_ms, 2 * renders + 1 + iterations  # renders, detections (+ target), plans
