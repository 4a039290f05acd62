"""The local stack: the four services as processes on this machine, wired together by URL.

Replicas of the renderer and detector get consecutive ports after the base ports; the controller
is told every replica's URL. Environment variables (``COSMOS_SCENES_DIR`` and the rest) pass
through to every process, with one service token for all of them (the stages serve the
controller with it, :mod:`services.common.auth`).
"""

from __future__ import annotations

import socket
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from services.common.auth import TOKEN_VARIABLE, new_token
from services.common.launch import (
    ServiceProcess,
    free_port,
    spawn_service,
    stop_service,
    wait_healthy,
)
from services.controller.keys import local_key

__all__ = ["ServicePlan", "Stack", "local_stack", "plan_stack", "running_stack"]

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
    """A running stack: the controller's URL, every process, and the service token a client
    of a stage sends."""

    controller: str
    renderers: tuple[str, ...]
    detectors: tuple[str, ...]
    optimizers: tuple[str, ...]
    processes: tuple[ServiceProcess, ...]
    service_token: str | None = field(default=None, repr=False)
    api_key: str | None = None
    """The controller's local admin key (:func:`services.controller.keys.local_key`), if known."""


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


@contextmanager
def running_stack(
    plan: list[ServicePlan],
    log_dir: Path,
    host: str = "127.0.0.1",
    timeout_s: float = 120.0,
    api_key: str | None = None,
) -> Iterator[Stack]:
    """Start the planned processes (stages first, all at once; then the controller) and stop
    them all when the block ends; ``api_key`` is handed on in the :class:`Stack`."""
    started: list[ServiceProcess] = []
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

        def urls(name: str) -> tuple[str, ...]:
            return tuple(
                proc.url for spec, proc in zip(plan, started, strict=True) if spec.name == name
            )

        yield Stack(
            controller=started[-1].url,
            renderers=urls("renderer"),
            detectors=urls("detector"),
            optimizers=urls("optimizer"),
            processes=tuple(started),
            service_token=started[-1].token,
            api_key=api_key,
        )
    finally:
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


@contextmanager
def local_stack(
    workdir: Path,
    *,
    renderers: int = 1,
    detectors: int = 1,
    env: Mapping[str, str] | None = None,
    host: str = "127.0.0.1",
) -> Iterator[Stack]:
    """A stack on free ports of ``host`` with a fresh SQLite database, its local API key and
    the logs in ``workdir``, stopped when the block ends (demos, tests, benchmarks)."""
    database_url = f"sqlite:///{workdir}/controller.sqlite3"
    ports = [_free_base(count, host) for count in (1, renderers, detectors, 1)]
    plan = plan_stack(
        host=host,
        controller_port=ports[0],
        renderer_port=ports[1],
        detector_port=ports[2],
        optimizer_port=ports[3],
        renderers=renderers,
        detectors=detectors,
        port_stride=LOCAL_STRIDE,
        database_url=database_url,
        env=env,
    )
    key = local_key(database_url)
    with running_stack(plan, workdir / "logs", host=host, api_key=key) as stack:
        yield stack
