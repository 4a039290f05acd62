"""The stages as processes and the controller's search loop over them, for benchmarks.

Renderer, detector and optimizer run as uvicorn processes on loopback (:func:`stage_processes`);
:class:`Controller` is the controller's own search loop over them, in this process, without its
HTTP API, wired by :func:`~services.controller.wiring.build_controller`: a search goes from
:meth:`~services.controller.submit.Admission.submit` through a
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
from services.common.contracts.search import TERMINAL_STATUSES, SearchOptions
from services.common.geometry.pose import Pose
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages
from services.controller.transport import Transport
from services.controller.wiring import Controller as Wired
from services.controller.wiring import build_controller

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
    own store and runner, wired as the service wires them (:func:`build_controller`), one
    search at a time; ``stages`` makes its stage calls. Its parts exist once :meth:`start` ran."""

    def __init__(
        self,
        urls: StageUrls,
        transport: Transport | None,
        database: Path,
        stages: type[Stages] = Stages,
    ) -> None:
        self.settings = ControllerSettings(
            controller_database_url=f"sqlite:///{database}",
            controller_renderer_urls=urls.renderer,
            controller_detector_urls=urls.detector,
            controller_optimizer_urls=urls.optimizer,
            controller_max_concurrent_searches=1,
            service_token=urls.token,
        )
        self._transport = transport
        self._stages_class = stages
        self._parts: Wired | None = None

    @property
    def parts(self) -> Wired:
        if self._parts is None:
            raise RuntimeError("the controller is not started")
        return self._parts

    @property
    def stages(self) -> Stages:
        return self.parts.stages

    async def start(self) -> None:
        """Build the controller and start its runner (the broker does not probe the stages:
        nothing but the searches calls them)."""
        self._parts = await build_controller(
            self.settings, transport=self._transport, stages_class=self._stages_class
        )
        await self._parts.runner.start()

    async def close(self) -> None:
        parts = self.parts
        # A worker cancelled before it has seen its search end takes the cancellation for the
        # search's and carries on (SearchRunner._work), and close() would wait for it forever.
        while parts.runner.running:
            await asyncio.sleep(0)
        await parts.close()

    async def _ended(self, search_id: str) -> None:
        notifier, store = self.parts.notifier, self.parts.store
        with notifier.following(search_id):
            while True:
                changed = notifier.current(search_id)
                state = store.status_doc(search_id)
                if state is not None and state[0] in TERMINAL_STATUSES:
                    return
                await changed.wait()

    async def search(
        self, target: Target, strategy: StrategyName, *, start: Pose, seed: int
    ) -> tuple[float, int]:
        """One search for ``target`` from ``start`` as ``POST /searches`` runs it: wall
        milliseconds and stage calls."""
        t0 = time.perf_counter()
        options = SearchOptions(
            scene=target.scene,
            strategy=strategy,
            start_theta_deg=start.theta_deg,
            start_phi_deg=start.phi_deg,
            seed=seed,
        )
        record = await self.parts.admission.submit(target.image, options, None)
        store = self.parts.store
        try:
            async with asyncio.timeout(SEARCH_TIMEOUT_S):
                await self._ended(record.id)
        except TimeoutError:
            state = store.status_doc(record.id)
            raise RuntimeError(f"search {record.id} still {state and state[0]}") from None
        wall_ms = (time.perf_counter() - t0) * 1000
        search = store.get(record.id)
        if search is None or search.status != "succeeded" or search.result is None:
            raise RuntimeError(f"search {record.id} ended {search and search.status}")
        iterations = len(store.iterations(record.id))
        renders = search.result.renders
        return wall_ms, 2 * renders + 1 + iterations  # renders, detections (+ target), plans
