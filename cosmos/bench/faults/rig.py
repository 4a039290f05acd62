"""The stack under fault: a local stack (:mod:`cosmos.stack`) on free loopback ports with its
processes as they run now, the means to kill and start them again, API keys of its tenants, and
the target images its normal searches look for.

The stack runs as plain processes: a killed one stays dead until :meth:`Rig.restart` starts it
again on its port, as an orchestrator would. Within :meth:`Rig.supervising` it runs as ``cosmos
up`` runs it: the same :class:`~cosmos.stack.Supervisor` starts every process that exits
again, on its port, after its backoff. One stack serves every scenario, so the suite pays for
one start-up.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from cosmos.bench.target import Target
from cosmos.launch import ServiceProcess, spawn_service, stop_service, wait_healthy
from cosmos.stack import ServicePlan, Stack, Supervisor, plan_local_stack, running_stack
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import GridIndex, PoseQuery
from services.controller.keys import KeyStore, local_key
from services.renderer.client import RendererClient

__all__ = ["FAR", "RIG_ENV", "Rig", "fault_rig", "wait_until"]

RIG_ENV: Mapping[str, str] = {
    # The load submits a short search every second or so per client: far more than the default
    # 30 a minute per key, which is a quota's business, not a fault's.
    "COSMOS_CONTROLLER_QUOTA_SEARCHES_PER_MINUTE": "100000",
}
SCENE = "demo"
FAR = (5, 6)
"""A grid pose away from the pole: the ``simple`` strategy started at θ = 7.5°, φ = 0 takes 12
iterations to reach it (the sentinel searches of :mod:`.scenarios`): long enough to be in flight
when a fault strikes, short enough to end soon after on a busy machine."""


class Rig:
    """A running local stack, as the fault scenarios see it."""

    def __init__(
        self,
        plan: list[ServicePlan],
        stack: Stack,
        log_dir: Path,
        *,
        targets: int = 4,
        seed: int = 15,
    ) -> None:
        self.plan = tuple(plan)
        self.stack = stack
        self.said: list[str] = []
        """What the supervisor said of every exit and restart."""
        self._log_dir = log_dir
        self._current = list(stack.processes)
        self._spawned: list[ServiceProcess] = []
        self._supervisor: Supervisor | None = None
        self._lock = threading.Lock()
        (controller,) = [p for p in plan if p.name == "controller"]
        self.controller_plan = controller
        self.database_url = controller.env["COSMOS_CONTROLLER_DATABASE_URL"]
        if stack.api_key is None:
            raise ValueError("the stack has no admin key")
        self.admin_key: str = stack.api_key
        """The local admin key (sees every tenant's searches)."""
        self.targets = self._render_targets(targets, seed)
        self.far_target = self._render(*FAR)

    @property
    def controller_url(self) -> str:
        return self.stack.controller

    @property
    def supervised(self) -> bool:
        """Whether a supervisor starts exited processes again now (:meth:`supervising`)."""
        return self._supervisor is not None

    @contextmanager
    def supervising(self) -> Iterator[Supervisor]:
        """The stack supervised as ``cosmos up`` supervises it (:class:`Supervisor`, its
        default backoff, exits and restarts told to :attr:`said`) for the block's duration."""
        if self._supervisor is not None:
            raise RuntimeError("the rig is supervised already")
        with self._lock:
            supervisor = Supervisor(self.plan, self._current, self._log_dir, say=self.said.append)
            self._supervisor = supervisor
        supervisor.start()
        try:
            yield supervisor
        finally:
            supervisor.stop()
            with self._lock:
                self._supervisor = None
                known = {id(process) for process in self._current}
                self._current = list(supervisor.processes)
                self._spawned += [p for p in self._current if id(p) not in known]

    def setting(self, name: str, default: str) -> str:
        """The controller's environment variable ``name`` as the rig set it, else ``default``."""
        return self.controller_plan.env.get(name, os.environ.get(name, default))

    def new_key(self, name: str) -> str:
        """A new tenant (not admin) key of the controller."""
        keys = KeyStore(self.database_url)
        try:
            _, key = keys.create(name)
        finally:
            keys.close()
        return key

    def processes(self) -> list[tuple[ServicePlan, ServiceProcess]]:
        """Every planned process and its incarnation now."""
        with self._lock:
            supervisor = self._supervisor
            current = supervisor.processes if supervisor is not None else tuple(self._current)
        return list(zip(self.plan, current, strict=True))

    def pids(self) -> list[tuple[str, int]]:
        """(service name, pid) of every process now (for :class:`~.harness.RssSampler`)."""
        return [(plan.name, process.process.pid) for plan, process in self.processes()]

    def replicas(self, name: str) -> list[ServiceProcess]:
        """The processes of the service ``name`` (``renderer``, ``detector``...), by port."""
        return [process for plan, process in self.processes() if plan.name == name]

    def kill(self, process: ServiceProcess) -> ServicePlan:
        """SIGKILL ``process`` and wait for it; its plan (to start it again)."""
        (plan,) = [p for p, s in self.processes() if s.url == process.url]
        os.kill(process.process.pid, signal.SIGKILL)
        process.process.wait(timeout=10)
        return plan

    def restart(self, plan: ServicePlan, timeout_s: float = 120.0) -> ServiceProcess:
        """Start ``plan``'s process again on its port, with its environment (the stack's token,
        the controller's database), and return once it is healthy. Not while
        :meth:`supervising`: the supervisor does this itself."""
        if self.supervised:
            raise RuntimeError("a supervised rig starts its processes again by itself")
        index = self.plan.index(plan)
        process = spawn_service(
            plan.app, self._log_dir, port=plan.port, env=plan.env, append_log=True
        )
        with self._lock:
            self._spawned.append(process)
            self._current[index] = process
        wait_healthy(process, timeout_s)
        return process

    def restarts(self, url: str) -> int:
        """How many times the process at ``url`` was started again (by the supervisor, or by
        :meth:`restart`)."""
        with self._lock:
            supervisor = self._supervisor
            spawned = sum(process.url == url for process in self._spawned)
        return spawned + (0 if supervisor is None else supervisor.restarts(url))

    def health(self) -> dict[str, Any] | None:
        """The controller's ``GET /health``, or None without an answer."""
        try:
            response = httpx.get(f"{self.controller_url}/health", timeout=5.0)
        except httpx.TransportError:
            return None
        if response.status_code != 200:
            return None
        body: dict[str, Any] = response.json()
        return body

    def replica_name(self, url: str) -> str:
        """The name the controller's ``/health`` gives the replica at ``url`` (``renderer-2``;
        it shows no addresses): its broker numbers a stage's replicas in the order it was given
        them, which is the stack's."""
        stages = (
            ("renderer", self.stack.renderers),
            ("detector", self.stack.detectors),
            ("optimizer", self.stack.optimizers),
        )
        for stage, urls in stages:
            if url in urls:
                return f"{stage}-{urls.index(url) + 1}"
        raise ValueError(f"{url} is no replica of this stack")

    def replica_up(self, url: str) -> bool:
        """Whether the controller's broker counts the replica at ``url`` as up."""
        health = self.health()
        name = self.replica_name(url)
        return health is not None and any(
            r["name"] == name and r["up"] for r in health.get("replicas", [])
        )

    def served(self, url: str) -> int:
        """How many tasks the broker says the replica at ``url`` has served."""
        health = self.health() or {}
        name = self.replica_name(url)
        return sum(int(r["served"]) for r in health.get("replicas", []) if r["name"] == name)

    def close(self) -> None:
        """Stop the processes this rig started itself (the stack stops its own)."""
        with self._lock:
            spawned = list(self._spawned)
        for process in spawned:
            stop_service(process)

    def _render(self, lat: int, lon: int) -> Target:
        with RendererClient(self.stack.renderers[0], token=self.stack.service_token) as client:
            grid = client.scene(SCENE).grid.grid()
            image = client.render_png(RenderRequest(scene=SCENE, pose=PoseQuery(lat=lat, lon=lon)))
        index = GridIndex(lat=lat, lon=lon)
        return Target(scene=SCENE, image=image, truth=index, pose=grid.pose(index))

    def _render_targets(self, count: int, seed: int) -> list[Target]:
        with RendererClient(self.stack.renderers[0], token=self.stack.service_token) as client:
            grid = client.scene(SCENE).grid.grid()
        rng = np.random.default_rng(seed)
        poses = [grid.unflat(int(i)) for i in rng.choice(grid.size, size=count, replace=False)]
        return [self._render(pose.lat, pose.lon) for pose in poses]


def wait_until(check: Callable[[], bool], timeout_s: float, interval_s: float = 0.1) -> float:
    """Seconds until ``check()`` held; TimeoutError after ``timeout_s``."""
    started = time.monotonic()
    while not check():
        if time.monotonic() - started > timeout_s:
            raise TimeoutError(f"not within {timeout_s:g} s")
        time.sleep(interval_s)
    return time.monotonic() - started


@contextmanager
def fault_rig(
    workdir: Path,
    *,
    renderers: int = 2,
    detectors: int = 1,
    env: Mapping[str, str] | None = None,
) -> Iterator[Rig]:
    """A local stack in ``workdir`` (fresh database, logs in ``logs/``) with :data:`RIG_ENV`
    and ``env``, as a :class:`Rig`; stopped when the block ends."""
    plan = plan_local_stack(
        workdir, renderers=renderers, detectors=detectors, env={**RIG_ENV, **(env or {})}
    )
    (controller,) = [p for p in plan if p.name == "controller"]
    admin = local_key(controller.env["COSMOS_CONTROLLER_DATABASE_URL"])
    logs = workdir / "logs"
    with running_stack(plan, logs, api_key=admin) as stack:
        rig = Rig(plan, stack, logs)
        try:
            yield rig
        finally:
            rig.close()
