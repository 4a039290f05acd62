"""Hosts of their own on one machine: Linux network namespaces on a bridge, each with its own
address, whose links can be cut, healed and impaired (latency, loss).

By default (:data:`DEFAULT`; ``COSMOS_TEST_HOSTS_NETWORK=prefix,bridge,subnet`` chooses others,
e.g. ``cz2,czbr1,10.252.0`` for a second copy of the tree on the same machine) every name starts
with ``cz`` and every address is in 10.251.0.0/24:

* the bridge ``czbr0``, with 10.251.0.1/24 in this (the root) namespace, so the test reaches
  every host directly;
* host ``i`` (0, 1, ...) is the namespace ``cz-<name>`` with its loopback up and a veth pair:
  ``czb<i>`` on the bridge, ``czh<i>`` inside the host with 10.251.0.(10 + i)/24.

Two hosts are partitioned from each other, and nobody else (:meth:`Host.partition`), by a
blackhole route to the other's address in each: new connections between them fail, and what
their open connections send is dropped, so a call in flight hangs as over a dead path.

A link is cut as a cable is pulled at the switch (``ip link set czb<i> down``): the host keeps
its address and its sockets, what was in flight is lost, TCP retransmits, and connections
survive a cut shorter than their timeouts. Healed, it is set up again.

Latency and loss (:meth:`Host.impair`) go on both ends of a host's link, the same in each
direction (a round trip gains twice the delay), with ``tc netem`` where the kernel has it
(:attr:`Network.netem`). Where it has not (``Specified qdisc kind is unknown``: no
``sch_netem``), no other qdisc delays a packet (tbf and htb only shape a rate), so:

* **loss** is still the kernel's: an htb root whose filter, a classic BPF program, sends each
  packet with probability ``loss`` (from the kernel's ``prandom``) to a class whose pfifo holds
  no packet (``limit 0``): dropped;
* **delay** is a userspace relay (:mod:`tests.hosts.relay`) in front of each service of a host
  placed with ``impairable``: it owns the host's service address and delays every chunk it
  forwards (only that service's traffic, not the host's probes to others).

Only one network exists at a time on a machine (a lock file, whatever the names); whatever
``cz*`` of its prefix it finds when it takes the lock was left by a run that died, and is
deleted first, its processes killed.
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from cosmos.launch import ROOT

__all__ = [
    "DEFAULT",
    "Addressing",
    "Host",
    "Network",
    "NetworkError",
    "namespace_problem",
]

FIRST_HOST = 10
ADDRESSING_VARIABLE = "COSMOS_TEST_HOSTS_NETWORK"
LOCK = Path("/run/lock/cz-hosts.lock")
# Classic BPF (tc's "bytecode"): A = a random 32-bit number (SKF_AD_OFF + SKF_AD_RANDOM); if
# A > keep the packet goes to class 1:2 (the pfifo of no room), else to the default class 1:1.
_RANDOM = 0xFFFFF000 + 56
_DROP_CLASS = 0x10002


@dataclass(frozen=True)
class Addressing:
    """The names and addresses of a network: namespaces ``<prefix>-<host>``, veths
    ``<prefix>b<i>`` and ``<prefix>h<i>``, the bridge, and the /24 ``<subnet>.0``."""

    prefix: str = "cz"
    bridge: str = "czbr0"
    subnet: str = "10.251.0"

    @property
    def gateway(self) -> str:
        return f"{self.subnet}.1"

    @property
    def cidr(self) -> str:
        return f"{self.subnet}.0/24"

    @classmethod
    def from_env(cls) -> Addressing:
        """:data:`DEFAULT`, or what ``COSMOS_TEST_HOSTS_NETWORK`` (``prefix,bridge,subnet``)
        says."""
        given = os.environ.get(ADDRESSING_VARIABLE, "").strip()
        if not given:
            return DEFAULT
        prefix, bridge, subnet = (part.strip() for part in given.split(","))
        return cls(prefix, bridge, subnet)


DEFAULT = Addressing()


class NetworkError(RuntimeError):
    """An ``ip`` or ``tc`` command failed; the message has its words."""


def _run(*command: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(command, capture_output=True, text=True, timeout=30, check=False)
    if check and done.returncode != 0:
        raise NetworkError(f"{' '.join(command)}: {done.stderr.strip() or done.stdout.strip()}")
    return done


def namespace_problem() -> str | None:
    """Why network namespaces cannot be made here (None: they can)."""
    if not Path("/proc/self/ns/net").exists():
        return "this system has no network namespaces (Linux only)"
    if os.geteuid() != 0:
        return "making network namespaces, veth pairs and a bridge needs root"
    try:
        _run("ip", "-V")
    except (FileNotFoundError, NetworkError) as exc:
        return f"no usable `ip` command (Debian's iproute2): {exc}"
    probe = f"{Addressing.from_env().prefix}-probe-{os.getpid()}"
    try:
        _run("ip", "netns", "add", probe)
    except NetworkError as exc:
        return f"`ip netns add` fails here: {exc}"
    _run("ip", "netns", "del", probe, check=False)
    return None


def _drop_program(loss: float) -> str:
    keep = min(int((1.0 - loss) * 2**32), 2**32 - 1)
    return f"4,32 0 0 {_RANDOM},37 0 1 {keep},6 0 0 {_DROP_CLASS},6 0 0 0"


def _lossy_root(device: str, loss: float) -> list[list[str]]:
    """The tc commands that drop each packet leaving ``device`` with probability ``loss``."""
    dev = ["dev", device]
    return [
        ["qdisc", "add", *dev, "root", "handle", "1:", "htb", "default", "1", "r2q", "100000"],
        ["class", "add", *dev, "parent", "1:", "classid", "1:1", "htb", "rate", "10gbit"],
        ["class", "add", *dev, "parent", "1:", "classid", "1:2", "htb", "rate", "10gbit"],
        ["qdisc", "add", *dev, "parent", "1:2", "handle", "2:", "pfifo", "limit", "0"],
        ["filter", "add", *dev, "parent", "1:", "protocol", "all", "prio", "1", "bpf"]
        + ["bytecode", _drop_program(loss)],
    ]


@dataclass
class Relay:
    """A delaying relay (:mod:`tests.hosts.relay`) in a host, in front of one service."""

    process: subprocess.Popen[str]
    listen: tuple[str, int]
    upstream_port: int

    def set_delay(self, delay_ms: float) -> None:
        stdin: IO[str] | None = self.process.stdin
        if stdin is None or self.process.poll() is not None:
            raise NetworkError(f"the relay on {self.listen} has exited")
        stdin.write(f"delay {delay_ms}\n")
        stdin.flush()
        # it answers each command with a line, so the delay holds once this returns
        if self.process.stdout is None or not self.process.stdout.readline():
            raise NetworkError(f"the relay on {self.listen} did not answer")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=10)
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                pipe.close()


@dataclass
class Host:
    """A host: a namespace with its own address on the bridge."""

    network: Network
    name: str
    index: int
    relays: list[Relay] = field(default_factory=list)

    @property
    def namespace(self) -> str:
        return f"{self.network.addressing.prefix}-{self.name}"

    @property
    def address(self) -> str:
        return f"{self.network.addressing.subnet}.{FIRST_HOST + self.index}"

    @property
    def bridge_end(self) -> str:
        """The veth on the bridge (the switch's port)."""
        return f"{self.network.addressing.prefix}b{self.index}"

    @property
    def host_end(self) -> str:
        """The veth inside the host."""
        return f"{self.network.addressing.prefix}h{self.index}"

    def command(self, *argv: str) -> list[str]:
        """``argv`` run inside this host."""
        return ["ip", "netns", "exec", self.namespace, *argv]

    @property
    def prefix(self) -> tuple[str, ...]:
        """What runs a command inside this host (for :func:`cosmos.launch.spawn_service`)."""
        return ("ip", "netns", "exec", self.namespace)

    def cut(self) -> None:
        """Pull the host's cable at the switch: nothing goes in or out until :meth:`heal`."""
        _run("ip", "link", "set", self.bridge_end, "down")

    def heal(self) -> None:
        _run("ip", "link", "set", self.bridge_end, "up")

    def partition(self, other: Host) -> None:
        """Cut this host off from ``other`` alone, both ways, until :meth:`rejoin`."""
        for one, two in ((self, other), (other, self)):
            _run(*one.prefix, "ip", "route", "add", "blackhole", f"{two.address}/32")

    def rejoin(self, other: Host) -> None:
        """Undo :meth:`partition`."""
        for one, two in ((self, other), (other, self)):
            _run(*one.prefix, "ip", "route", "del", "blackhole", f"{two.address}/32", check=False)

    def impair(self, *, delay_ms: float = 0.0, loss: float = 0.0) -> None:
        """Add ``delay_ms`` one way and lose a fraction ``loss`` of packets in each direction of
        the host's link, until :meth:`clear` (netem where the kernel has it, else the module's
        docstring says how)."""
        if delay_ms < 0 or not 0.0 <= loss < 1.0:
            raise ValueError("delay_ms must be >= 0 and loss in [0, 1)")
        self.clear()
        if self.network.netem:
            netem = ["netem", "delay", f"{delay_ms}ms", "loss", f"{loss * 100:.3f}%"]
            for tc, device in self._ends():
                _run(*tc, "qdisc", "add", "dev", device, "root", *netem)
            return
        if delay_ms > 0 and not self.relays:
            raise NetworkError(
                f"{self.name}: this kernel has no netem, and the host was placed without a "
                "relay (impairable=False), so nothing can delay its traffic"
            )
        if loss > 0:
            for tc, device in self._ends():
                for step in _lossy_root(device, loss):
                    _run(*tc, *step)
        for relay in self.relays:
            relay.set_delay(delay_ms)

    def clear(self) -> None:
        """No delay and no loss on the host's link."""
        for tc, device in self._ends():
            _run(*tc, "qdisc", "del", "dev", device, "root", check=False)
        for relay in self.relays:
            relay.set_delay(0.0)

    def _ends(self) -> list[tuple[tuple[str, ...], str]]:
        """Each end of the host's link: the ``tc`` that reaches it, and its device."""
        return [(("tc",), self.bridge_end), ((*self.prefix, "tc"), self.host_end)]

    def relay(self, port: int, upstream_port: int, log: Path) -> Relay:
        """Start a relay on this host's ``address:port`` that forwards to ``address:upstream
        _port`` (without delay until :meth:`impair` says otherwise)."""
        log.parent.mkdir(parents=True, exist_ok=True)
        argv = ["-m", "tests.hosts.relay", f"{self.address}:{port}", f"{upstream_port}"]
        with log.open("ab") as sink:
            process = subprocess.Popen(
                self.command(sys.executable, *argv),
                cwd=ROOT,  # the relay runs from the repository, as the services do
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=sink,
                text=True,
            )
        relay = Relay(process, (self.address, port), upstream_port)
        self.relays.append(relay)
        ready = process.stdout.readline() if process.stdout is not None else ""
        if ready.strip() != "ready":
            relay.stop()
            raise NetworkError(f"the relay on {self.address}:{port} did not start (log: {log})")
        return relay


class Network:
    """The bridge and its hosts; :meth:`open` builds the bridge, :meth:`close` removes all.

    ``netem`` says whether this kernel has ``tc netem`` (probed on the bridge when opened)."""

    def __init__(self, addressing: Addressing = DEFAULT) -> None:
        self.addressing = addressing
        self.hosts: dict[str, Host] = {}
        self.netem = False
        self._lock: IO[bytes] | None = None
        self._cleanups: list[Callable[[], None]] = []

    def open(self) -> Network:
        LOCK.parent.mkdir(parents=True, exist_ok=True)
        self._lock = LOCK.open("ab")
        fcntl.flock(self._lock, fcntl.LOCK_EX)  # another run waits until this one is gone
        try:
            remove_stale(self.addressing)
            bridge = self.addressing.bridge
            _run("ip", "link", "add", bridge, "type", "bridge")
            _run("ip", "addr", "add", f"{self.addressing.gateway}/24", "dev", bridge)
            _run("ip", "link", "set", bridge, "up")
            self.netem = _has_netem(bridge)
        except BaseException:
            self.close()
            raise
        return self

    def add_host(self, name: str) -> Host:
        """A new host ``name`` with its loopback up and its link to the bridge up."""
        if name in self.hosts:
            raise ValueError(f"there is a host {name!r} already")
        host = Host(self, name, len(self.hosts))
        self.hosts[name] = host
        _run("ip", "netns", "add", host.namespace)
        _run("ip", "link", "add", host.bridge_end, "type", "veth", "peer", "name", host.host_end)
        _run("ip", "link", "set", host.host_end, "netns", host.namespace)
        _run("ip", "link", "set", host.bridge_end, "master", self.addressing.bridge)
        _run("ip", "link", "set", host.bridge_end, "up")
        inside = host.prefix
        _run(*inside, "ip", "addr", "add", f"{host.address}/24", "dev", host.host_end)
        _run(*inside, "ip", "link", "set", host.host_end, "up")
        _run(*inside, "ip", "link", "set", "lo", "up")
        return host

    def on_close(self, cleanup: Callable[[], None]) -> None:
        """Run ``cleanup`` when the network closes, before its hosts go (last added, first)."""
        self._cleanups.append(cleanup)

    def close(self) -> None:
        """Stop what runs on the hosts, delete the hosts and the bridge, release the lock (once:
        without the lock, the ``cz*`` things may be another run's)."""
        if self._lock is None:
            return
        try:
            while self._cleanups:
                try:
                    self._cleanups.pop()()
                except Exception:  # one failed cleanup must not keep the rest from running
                    continue
            for host in self.hosts.values():
                for relay in host.relays:
                    relay.stop()
            remove_stale(self.addressing)
            self.hosts.clear()
        finally:
            self._lock.close()  # releases the flock
            self._lock = None

    def __enter__(self) -> Network:
        return self.open()

    def __exit__(self, *_: object) -> None:
        self.close()


def _has_netem(bridge: str) -> bool:
    tried = _run("tc", "qdisc", "add", "dev", bridge, "root", "netem", "delay", "1ms", check=False)
    if tried.returncode == 0:
        _run("tc", "qdisc", "del", "dev", bridge, "root", check=False)
    return tried.returncode == 0


def _names(lines: Sequence[str]) -> list[str]:
    return [line.split()[0].split("@")[0].rstrip(":") for line in lines if line.strip()]


def remove_stale(addressing: Addressing = DEFAULT) -> None:
    """Delete every namespace of ``addressing`` (its processes killed first), its veths and its
    bridge."""
    prefix = addressing.prefix
    spaces = _names(_run("ip", "netns", "list", check=False).stdout.splitlines())
    for space in [s for s in spaces if s.startswith(f"{prefix}-")]:
        pids = _run("ip", "netns", "pids", space, check=False).stdout.split()
        for pid in pids:
            try:
                os.kill(int(pid), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                continue
        _wait_gone([int(p) for p in pids if p.isdigit()])
        _run("ip", "netns", "del", space, check=False)
    links = _run("ip", "-o", "link", "show", check=False).stdout.splitlines()
    ours = (f"{prefix}b", f"{prefix}h", addressing.bridge)
    for link in [line.split(":")[1].strip().split("@")[0] for line in links if ":" in line]:
        if link.startswith(ours):
            _run("ip", "link", "del", link, check=False)


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"  # a zombie holds no socket


def _wait_gone(pids: Sequence[int], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    for pid in pids:
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.02)
