"""Start services as local uvicorn processes on loopback, wait until healthy, stop them.

Every process runs with a service token (:mod:`services.common.auth`): the one its environment
gives, else a new one of its own; :attr:`ServiceProcess.token` says which, for its callers.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from services.common.auth import TOKEN_VARIABLE, bearer, new_token

__all__ = [
    "ServiceProcess",
    "free_port",
    "running_service",
    "spawn_service",
    "start_service",
    "stop_service",
    "wait_healthy",
]

ROOT = Path(__file__).resolve().parents[1]


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


@dataclass(frozen=True)
class ServiceProcess:
    """A running service: its base URL, process, log file and service token."""

    url: str
    process: subprocess.Popen[bytes]
    log: Path
    token: str | None = field(default=None, repr=False)

    @property
    def headers(self) -> dict[str, str]:
        """What a request must carry to be served (the token as ``Authorization: Bearer``)."""
        return bearer(self.token)


def spawn_service(
    app: str,
    log_dir: Path,
    *,
    port: int | None = None,
    host: str = "127.0.0.1",
    env: Mapping[str, str] | None = None,
    append_log: bool = False,
    prefix: Sequence[str] = (),
) -> ServiceProcess:
    """Start ``<app>`` under uvicorn without waiting for it (see :func:`wait_healthy`), with the
    request head limits of :mod:`services.common.server` and ``COSMOS_SERVICE_TOKEN`` from
    ``env``, else from this process's environment, else a new one. Its output goes to
    ``<service>-<port>.log`` in ``log_dir`` (after what is there with ``append_log``, for a
    process started again). ``prefix`` runs it through a command that execs it (``ip netns exec
    NAME``: a host of its own, ``host`` its address there), so the process's id is the
    service's."""
    port = port or free_port(host)
    log_dir.mkdir(parents=True, exist_ok=True)
    log = log_dir / f"{app.split('.')[1] if app.count('.') >= 1 else app}-{port}.log"
    environ = {**os.environ, **(env or {})}
    environ[TOKEN_VARIABLE] = environ.get(TOKEN_VARIABLE) or new_token()
    server = [sys.executable, "-m", "services.common.server"]
    with log.open("ab" if append_log else "wb") as sink:
        process = subprocess.Popen(
            [*prefix, *server, app, "--host", host, "--port", str(port)],
            cwd=ROOT,
            env=environ,
            stdout=sink,
            stderr=subprocess.STDOUT,
        )
    return ServiceProcess(
        url=f"http://{host}:{port}", process=process, log=log, token=environ[TOKEN_VARIABLE]
    )


def wait_healthy(service: ServiceProcess, timeout_s: float = 60.0) -> None:
    """Return once ``GET /health`` answers 200; raise ``RuntimeError`` with the log's tail if the
    process exits or stays unhealthy (and stop it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if service.process.poll() is not None:
            raise RuntimeError(
                f"{service.url} exited with {service.process.returncode}:\n{_tail(service.log)}"
            )
        try:
            if httpx.get(f"{service.url}/health", timeout=2.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline:
            stop_service(service)
            raise RuntimeError(
                f"{service.url} was not healthy after {timeout_s:.0f} s:\n{_tail(service.log)}"
            )
        time.sleep(0.1)


def start_service(
    app: str,
    log_dir: Path,
    *,
    port: int | None = None,
    host: str = "127.0.0.1",
    env: Mapping[str, str] | None = None,
    timeout_s: float = 60.0,
) -> ServiceProcess:
    """Run ``uvicorn <app>`` and return once ``GET /health`` answers 200."""
    service = spawn_service(app, log_dir, port=port, host=host, env=env)
    wait_healthy(service, timeout_s)
    return service


def stop_service(service: ServiceProcess, timeout_s: float = 15.0) -> None:
    """SIGTERM, then SIGKILL if the process has not exited after ``timeout_s``."""
    if service.process.poll() is not None:
        return
    service.process.terminate()
    try:
        service.process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        service.process.kill()
        service.process.wait(timeout=5)


@contextmanager
def running_service(
    app: str, log_dir: Path, env: Mapping[str, str] | None = None, timeout_s: float = 60.0
) -> Iterator[ServiceProcess]:
    """A service on a free loopback port for the duration of the block."""
    service = start_service(app, log_dir, env=env, timeout_s=timeout_s)
    try:
        yield service
    finally:
        stop_service(service)


def _tail(log: Path, chars: int = 4000) -> str:
    try:
        return log.read_text(errors="replace")[-chars:]
    except OSError:
        return "(no log)"
