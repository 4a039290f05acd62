"""The project's services on hosts of their own (:mod:`tests.hosts.network`): one service per
host, bound to that host's address, started as :mod:`cosmos.stack` starts them (uvicorn through
:mod:`services.common.server`, :func:`cosmos.launch.spawn_service`, one service token for all),
and the controller configured only by the stages' addresses.

A cluster is its hosts, one :class:`HostSpec` line each; adding a host is adding a line::

    TOPOLOGY = (
        HostSpec("controller-1", CONTROLLER),
        HostSpec("renderer-1", RENDERER),
        HostSpec("renderer-2", RENDERER),
        HostSpec("detector-1", DETECTOR, impairable=True),
        ...
    )

Roles start tier by tier (stages, then controllers), each tier once the one before is healthy,
so a second controller is ``HostSpec("controller-2", CONTROLLER)``. A database of its own (the
PostgreSQL store, :mod:`tests.hosts.database`) runs on a host added to the network before the
cluster starts, and ``database_url=`` names its address; every controller gets the same.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cosmos.launch import ServiceProcess, spawn_service, stop_service, wait_healthy
from services.common.auth import TOKEN_VARIABLE, new_token
from services.controller.keys import KeyStore, local_key
from services.controller.store import is_postgres_url
from tests.hosts.network import Host, Network

__all__ = [
    "CONTROLLER",
    "DETECTOR",
    "OPTIMIZER",
    "RENDERER",
    "STAGES",
    "Cluster",
    "HostSpec",
    "Role",
]

INNER_PORT_OFFSET = 10000  # a service behind a relay listens this far above its public port


@dataclass(frozen=True)
class Role:
    """What runs on a host: a service's app, its port, its tier (lower tiers start first)."""

    name: str
    app: str
    port: int
    tier: int = 1

    def env(self, cluster: Cluster) -> dict[str, str]:
        """The service's own variables, beyond what every service of the cluster gets."""
        return {}

    def spawn(
        self, host: Host, port: int, env: Mapping[str, str], log_dir: Path, *, again: bool
    ) -> ServiceProcess:
        """Start the service on ``host``'s address and ``port`` (not waiting for it)."""
        return spawn_service(
            self.app,
            log_dir,
            port=port,
            host=host.address,
            env=env,
            append_log=again,
            prefix=host.prefix,
        )

    def wait(self, process: ServiceProcess, timeout_s: float) -> None:
        """Return once the service answers (its ``/health``)."""
        wait_healthy(process, timeout_s)


@dataclass(frozen=True)
class ControllerRole(Role):
    """The controller: told every stage replica by address, and the cluster's database."""

    tier: int = 2

    def env(self, cluster: Cluster) -> dict[str, str]:
        return {
            "COSMOS_CONTROLLER_RENDERER_URLS": ",".join(cluster.urls(RENDERER)),
            "COSMOS_CONTROLLER_DETECTOR_URLS": ",".join(cluster.urls(DETECTOR)),
            "COSMOS_CONTROLLER_OPTIMIZER_URLS": ",".join(cluster.urls(OPTIMIZER)),
            "COSMOS_CONTROLLER_DATABASE_URL": cluster.database_url,
            **cluster.controller_env,
        }


RENDERER = Role("renderer", "services.renderer.app:app", 8001)
DETECTOR = Role("detector", "services.detector.app:app", 8002)
OPTIMIZER = Role("optimizer", "services.optimizer.app:app", 8003)
CONTROLLER = ControllerRole("controller", "services.controller.app:app", 8000)
STAGES = (RENDERER, DETECTOR, OPTIMIZER)


@dataclass(frozen=True)
class HostSpec:
    """A host ``name`` running ``role``; ``impairable``: its link may be given latency (where
    the kernel has no netem, a relay then stands in front of its service from the start)."""

    name: str
    role: Role
    impairable: bool = False


@dataclass
class _Placed:
    spec: HostSpec
    host: Host
    process: ServiceProcess | None = None
    starts: int = 0

    @property
    def inner_port(self) -> int:
        """The port the service listens on: its role's, or further up behind a relay."""
        port = self.spec.role.port
        return port + INNER_PORT_OFFSET if self.host.relays else port


@dataclass
class Cluster:
    """The hosts of ``specs`` on ``network``, each running its role, logs under ``workdir``.

    ``env`` goes to every service, ``controller_env`` to controllers too; the database is
    ``database_url`` (default: SQLite in ``workdir``, which every host sees: namespaces split
    the network, not the disk)."""

    network: Network
    specs: Sequence[HostSpec]
    workdir: Path
    env: Mapping[str, str] = field(default_factory=dict)
    controller_env: Mapping[str, str] = field(default_factory=dict)
    database_url: str = ""
    token: str = field(default_factory=new_token, repr=False)
    timeout_s: float = 120.0
    _placed: dict[str, _Placed] = field(default_factory=dict, repr=False)
    _api_key: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not self.database_url:
            self.database_url = f"sqlite:///{self.workdir}/controller.sqlite3"
        names = [spec.name for spec in self.specs]
        if len(set(names)) != len(names):
            raise ValueError(f"host names repeat: {names}")

    # -- what runs where -----------------------------------------------------------------------

    def host(self, name: str) -> Host:
        return self._placed[name].host

    def process(self, name: str) -> ServiceProcess:
        process = self._placed[name].process
        if process is None:
            raise LookupError(f"nothing runs on {name}")
        return process

    def url(self, name: str) -> str:
        """The service's URL: its host's address and its role's port."""
        placed = self._placed[name]
        return f"http://{placed.host.address}:{placed.spec.role.port}"

    def names(self, role: Role) -> list[str]:
        return [spec.name for spec in self.specs if spec.role.name == role.name]

    def urls(self, role: Role) -> list[str]:
        return [self.url(name) for name in self.names(role)]

    @property
    def api_key(self) -> str:
        """The database's local admin key (made on first use)."""
        if self._api_key is None and is_postgres_url(self.database_url):
            keys = KeyStore(self.database_url)  # a shared database has no local key file
            try:
                self._api_key = keys.create("hosts test", admin=True)[1]
            finally:
                keys.close()
        if self._api_key is None:
            self._api_key = local_key(self.database_url)
        return self._api_key

    @property
    def headers(self) -> dict[str, str]:
        """What a call to a controller carries: the API key."""
        return {"Authorization": f"Bearer {self.api_key}"}

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> Cluster:
        """Make the hosts, then start their services tier by tier, each tier all at once."""
        self.network.on_close(self.stop)
        for spec in self.specs:
            host = self.network.add_host(spec.name)
            self._placed[spec.name] = _Placed(spec, host)
            if spec.impairable and not self.network.netem:
                host.relay(
                    spec.role.port,
                    spec.role.port + INNER_PORT_OFFSET,
                    self._log_dir(spec.name) / "relay.log",
                )
        for tier in sorted({spec.role.tier for spec in self.specs}):
            names = [spec.name for spec in self.specs if spec.role.tier == tier]
            for name in names:
                self._spawn(name)
            for name in names:
                self._placed[name].spec.role.wait(self.process(name), self.timeout_s)
        return self

    def _log_dir(self, name: str) -> Path:
        return self.workdir / "logs" / name

    def _spawn(self, name: str) -> None:
        placed = self._placed[name]
        role = placed.spec.role
        env = {**self.env, TOKEN_VARIABLE: self.token, **role.env(self)}
        placed.process = role.spawn(
            placed.host, placed.inner_port, env, self._log_dir(name), again=placed.starts > 0
        )
        placed.starts += 1

    def kill(self, name: str) -> None:
        """SIGKILL the service on host ``name`` (nothing of it is left running)."""
        process = self.process(name).process
        os.kill(process.pid, signal.SIGKILL)
        process.wait(timeout=10)

    def restart(self, name: str) -> ServiceProcess:
        """Start host ``name``'s service again (same address, port and settings); return once
        it answers."""
        if self.process(name).process.poll() is None:
            raise RuntimeError(f"the service on {name} still runs")
        self._spawn(name)
        process = self.process(name)
        self._placed[name].spec.role.wait(process, self.timeout_s)
        return process

    def stop(self) -> None:
        """Stop every service, controllers first."""
        for placed in sorted(self._placed.values(), key=lambda p: -p.spec.role.tier):
            if placed.process is not None:
                stop_service(placed.process)
