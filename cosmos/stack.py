"""The local stack: the four services as processes on this machine, wired together by URL.

Replicas of the renderer and detector get consecutive ports after the base ports; the controller
is told every replica's URL. Environment variables (``COSMOS_SCENES_DIR`` and the rest) pass
through to every process, with one service token for all of them (the stages serve the
controller with it, :mod:`services.common.auth`).

Supervised (``cosmos up``), a process that exits is started again on its port after a backoff
(:class:`Supervisor`) while the others go on serving; the broker sends work to the other
replicas of a stage meanwhile.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from cosmos.launch import (
    ServiceProcess,
    free_port,
    spawn_service,
    stop_service,
    wait_healthy,
)
from services.common.auth import TOKEN_VARIABLE, new_token
from services.controller.keys import local_key

__all__ = [
    "ServicePlan",
    "Stack",
    "Supervisor",
    "local_stack",
    "plan_local_stack",
    "plan_stack",
    "restart_delay",
    "running_stack",
]

_log = logging.getLogger("cosmos.stack")

LOCAL_STRIDE = 10  # port step between replicas of a stage in :func:`local_stack`


@dataclass(frozen=True)
class ServicePlan:
    """One process to start."""

    name: str
    app: str
    port: int
    env: Mapping[str, str]


@dataclass(frozen=True)
class Stack:
    """A running stack: the controller's URL, every process as started, the service token a
    client of a stage sends, and the supervisor that starts exited processes again (if any)."""

    controller: str
    renderers: tuple[str, ...]
    detectors: tuple[str, ...]
    optimizers: tuple[str, ...]
    processes: tuple[ServiceProcess, ...]
    service_token: str | None = field(default=None, repr=False)
    api_key: str | None = None
    """The controller's local admin key (:func:`services.controller.keys.local_key`), if known."""
    supervisor: Supervisor | None = None


def plan_stack(
    *,
    host: str = "127.0.0.1",
    controller_port: int = 8000,
    renderer_port: int = 8001,
    detector_port: int = 8002,
    optimizer_port: int = 8003,
    renderers: int = 1,
    detectors: int = 1,
    optimizers: int = 1,
    port_stride: int = 10,
    database_url: str | None = None,
    env: Mapping[str, str] | None = None,
    service_token: str | None = None,
) -> list[ServicePlan]:
    """The processes of a stack; replica ``i`` of a stage listens on ``port + i * port_stride``.
    Every process gets ``service_token`` (a new one when None)."""
    if min(renderers, detectors, optimizers) < 1:
        raise ValueError("every stage needs at least one replica")
    base = {**(env or {}), TOKEN_VARIABLE: service_token or new_token()}

    def replicas(name: str, port: int, count: int) -> list[ServicePlan]:
        return [
            ServicePlan(name, f"services.{name}.app:app", port + i * port_stride, base)
            for i in range(count)
        ]

    stages = (
        replicas("renderer", renderer_port, renderers)
        + replicas("detector", detector_port, detectors)
        + replicas("optimizer", optimizer_port, optimizers)
    )

    def urls(name: str) -> str:
        return ",".join(f"http://{host}:{p.port}" for p in stages if p.name == name)

    controller_env = {
        **base,
        "COSMOS_CONTROLLER_RENDERER_URLS": urls("renderer"),
        "COSMOS_CONTROLLER_DETECTOR_URLS": urls("detector"),
        "COSMOS_CONTROLLER_OPTIMIZER_URLS": urls("optimizer"),
    }
    if database_url is not None:
        controller_env["COSMOS_CONTROLLER_DATABASE_URL"] = database_url
    controller = ServicePlan(
        "controller", "services.controller.app:app", controller_port, controller_env
    )
    return [*stages, controller]


def restart_delay(
    previous_s: float | None,
    uptime_s: float,
    *,
    first_s: float = 0.5,
    max_s: float = 30.0,
    stable_s: float = 60.0,
) -> float:
    """Seconds to wait before starting again a process that exited after ``uptime_s``:
    ``first_s`` the first time and after a run of ``stable_s`` or more, else twice the previous
    wait (``previous_s``), at most ``max_s``."""
    if previous_s is None or uptime_s >= stable_s:
        return first_s
    return min(previous_s * 2.0, max_s)


class _Slot:
    """One planned process and its current incarnation."""

    def __init__(self, plan: ServicePlan, process: ServiceProcess) -> None:
        self.plan = plan
        self.process = process
        self.started_at = time.monotonic()
        self.delay_s: float | None = None
        self.restart_at: float | None = None
        self.restarts = 0


class Supervisor:
    """Starts each process of a stack again when it exits, on the same port, with exponential
    backoff (:func:`restart_delay`), until :meth:`stop`; tells ``say`` of every exit and restart.

    :meth:`check` does one round (tests call it); :meth:`start` runs rounds on a thread.
    """

    def __init__(
        self,
        plan: Sequence[ServicePlan],
        processes: Sequence[ServiceProcess],
        log_dir: Path,
        host: str = "127.0.0.1",
        *,
        first_delay_s: float = 0.5,
        max_delay_s: float = 30.0,
        stable_s: float = 60.0,
        interval_s: float = 0.2,
        say: Callable[[str], None] = _log.warning,
    ) -> None:
        self._slots = [_Slot(p, s) for p, s in zip(plan, processes, strict=True)]
        self._log_dir = log_dir
        self._host = host
        self._delays = {"first_s": first_delay_s, "max_s": max_delay_s, "stable_s": stable_s}
        self._interval_s = interval_s
        self._say = say
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def processes(self) -> tuple[ServiceProcess, ...]:
        """Every process as it runs now (a restarted one in its new incarnation)."""
        with self._lock:
            return tuple(slot.process for slot in self._slots)

    def restarts(self, url: str) -> int:
        """How many times the process at ``url`` was started again."""
        with self._lock:
            return sum(slot.restarts for slot in self._slots if slot.process.url == url)

    def check(self) -> None:
        """Notice the processes that exited, and start again those whose wait is over."""
        with self._lock:
            for slot in self._slots:
                if self._stopped.is_set():
                    return
                self._check(slot)

    def _check(self, slot: _Slot) -> None:
        process = slot.process
        now = time.monotonic()
        if slot.restart_at is None:
            code = process.process.poll()
            if code is None:
                return
            slot.delay_s = restart_delay(slot.delay_s, now - slot.started_at, **self._delays)
            slot.restart_at = now + slot.delay_s
            how = f"signal {-code}" if code < 0 else f"status {code}"
            self._say(
                f"{slot.plan.name} {process.url} exited ({how}); starting it again in "
                f"{slot.delay_s:g} s (log: {process.log})"
            )
            return
        if now < slot.restart_at:
            return
        slot.process = spawn_service(
            slot.plan.app,
            self._log_dir,
            port=slot.plan.port,
            host=self._host,
            env=slot.plan.env,
            append_log=True,
        )
        slot.started_at, slot.restart_at = now, None
        slot.restarts += 1
        self._say(
            f"{slot.plan.name} {process.url} started again (restart {slot.restarts}, "
            f"pid {slot.process.process.pid})"
        )

    def start(self) -> None:
        """Check every ``interval_s`` on a daemon thread until :meth:`stop`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="cosmos-supervisor", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while not self._stopped.wait(self._interval_s):
            try:
                self.check()
            except Exception:  # one failed start must not end the supervision of the rest
                _log.exception("supervising the stack failed")

    def stop(self) -> None:
        """Start nothing more (the processes keep running; stop them next)."""
        self._stopped.set()
        if self._thread is not None:
            self._thread.join()


@contextmanager
def running_stack(
    plan: list[ServicePlan],
    log_dir: Path,
    host: str = "127.0.0.1",
    timeout_s: float = 120.0,
    api_key: str | None = None,
    *,
    supervise: bool = False,
    say: Callable[[str], None] = _log.warning,
) -> Iterator[Stack]:
    """Start the planned processes (stages first, all at once; then the controller) and stop
    them all when the block ends; ``api_key`` is handed on in the :class:`Stack`. ``supervise``
    starts each again when it exits, until then (:class:`Supervisor`, which tells ``say`` of
    each exit and restart)."""
    started: list[ServiceProcess] = []
    supervisor: Supervisor | None = None
    try:
        stages = [p for p in plan if p.name != "controller"]
        for service in stages:
            started.append(
                spawn_service(service.app, log_dir, port=service.port, host=host, env=service.env)
            )
        for process in started:
            wait_healthy(process, timeout_s)
        (controller,) = [p for p in plan if p.name == "controller"]
        started.append(
            spawn_service(
                controller.app, log_dir, port=controller.port, host=host, env=controller.env
            )
        )
        wait_healthy(started[-1], timeout_s)
        order = [*stages, controller]
        if supervise:
            supervisor = Supervisor(order, started, log_dir, host, say=say)
            supervisor.start()

        def urls(name: str) -> tuple[str, ...]:
            return tuple(
                proc.url for spec, proc in zip(order, started, strict=True) if spec.name == name
            )

        yield Stack(
            controller=started[-1].url,
            renderers=urls("renderer"),
            detectors=urls("detector"),
            optimizers=urls("optimizer"),
            processes=tuple(started),
            service_token=started[-1].token,
            api_key=api_key,
            supervisor=supervisor,
        )
    finally:
        if supervisor is not None:
            supervisor.stop()
            started = list(supervisor.processes)
        for process in reversed(started):
            stop_service(process)


def _free_base(count: int, host: str) -> int:
    """A port ``p`` with ``p + i * LOCAL_STRIDE`` free for every replica ``i < count``."""
    for _ in range(100):
        base = free_port(host)
        if base + (count - 1) * LOCAL_STRIDE > 65535:
            continue
        try:
            for i in range(1, count):
                with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
                    sock.bind((host, base + i * LOCAL_STRIDE))
        except OSError:
            continue
        return base
    raise RuntimeError(f"no {count} free ports {LOCAL_STRIDE} apart on {host}")


def plan_local_stack(
    workdir: Path,
    *,
    renderers: int = 1,
    detectors: int = 1,
    env: Mapping[str, str] | None = None,
    host: str = "127.0.0.1",
) -> list[ServicePlan]:
    """A stack on free ports of ``host`` with a fresh SQLite database in ``workdir``."""
    ports = [_free_base(count, host) for count in (1, renderers, detectors, 1)]
    return plan_stack(
        host=host,
        controller_port=ports[0],
        renderer_port=ports[1],
        detector_port=ports[2],
        optimizer_port=ports[3],
        renderers=renderers,
        detectors=detectors,
        port_stride=LOCAL_STRIDE,
        database_url=_local_database(workdir),
        env=env,
    )


def _local_database(workdir: Path) -> str:
    return f"sqlite:///{workdir}/controller.sqlite3"


@contextmanager
def local_stack(
    workdir: Path,
    *,
    renderers: int = 1,
    detectors: int = 1,
    env: Mapping[str, str] | None = None,
    host: str = "127.0.0.1",
) -> Iterator[Stack]:
    """:func:`plan_local_stack` running, with its local API key and the logs in ``workdir``,
    stopped when the block ends (demos, tests, benchmarks)."""
    plan = plan_local_stack(workdir, renderers=renderers, detectors=detectors, env=env, host=host)
    key = local_key(_local_database(workdir))
    with running_stack(plan, workdir / "logs", host=host, api_key=key) as stack:
        yield stack
