"""The hosts harness does what it says: a host answers on its own address, a cut link carries
nothing until healed, loss drops about the fraction asked for, latency delays a round trip by
twice the one-way delay, and closing the network leaves no ``cz*`` namespace or link behind."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from cosmos.launch import ROOT
from tests.hosts.network import Addressing, Host, Network

pytestmark = pytest.mark.hosts

PORT = 8080
ECHO = """
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind((sys.argv[1], int(sys.argv[2])))
s.settimeout(float(sys.argv[3]))
print("ready", flush=True)
n = 0
try:
    while True:
        s.recv(64)
        n += 1
except TimeoutError:
    pass
print(n)
"""


@contextmanager
def http_server(host: Host, logs: Path, port: int = PORT) -> Iterator[str]:
    """Python's HTTP file server on ``host``'s address (behind a relay on ``port`` where the
    kernel has no netem); its URL."""
    inner = port + 1 if not host.network.netem else port
    if inner != port:
        host.relay(port, inner, logs / "relay.log")
    argv = [sys.executable, "-m", "http.server", "--bind", host.address, str(inner)]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    server = subprocess.Popen(host.command(*argv), cwd=ROOT / "scenes", **quiet)
    url = f"http://{host.address}:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                httpx.get(f"{url}/demo.yaml", timeout=1.0)
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "the HTTP server did not start"
                time.sleep(0.1)
        yield url
    finally:
        server.kill()
        server.wait(timeout=10)


def fetch_s(url: str) -> float:
    """Seconds for one GET on a new connection."""
    started = time.perf_counter()
    response = httpx.get(f"{url}/demo.yaml", timeout=10.0)
    assert response.status_code == 200
    return time.perf_counter() - started


def test_a_host_answers_on_its_address_and_a_cut_link_carries_nothing_until_healed(
    network, tmp_path
):
    host = network.add_host("web")
    assert host.address.startswith(f"{network.addressing.subnet}.")
    with http_server(host, tmp_path) as url:
        fetch_s(url)
        host.cut()
        with pytest.raises(httpx.TransportError):
            httpx.get(f"{url}/demo.yaml", timeout=1.0)
        host.heal()
        deadline = time.monotonic() + 10
        while True:
            try:
                fetch_s(url)
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "the healed link carries nothing"


def test_latency_delays_a_round_trip_by_twice_the_one_way_delay(network, tmp_path, say):
    host = network.add_host("web")
    delay_s = 0.3
    with http_server(host, tmp_path) as url:
        before = min(fetch_s(url) for _ in range(3))
        host.impair(delay_ms=delay_s * 1000)
        slowed = min(fetch_s(url) for _ in range(3))
        host.clear()
        after = min(fetch_s(url) for _ in range(3))
    say(
        f"GET {before * 1e3:.0f} ms; {delay_s * 1e3:.0f} ms each way {slowed * 1e3:.0f} ms; "
        f"cleared {after * 1e3:.0f} ms"
    )
    assert slowed >= 2 * delay_s  # a request and its answer, each delayed
    assert after < 2 * delay_s  # cleared, the delay is gone


def test_loss_drops_about_the_fraction_asked_for(network, say):
    host = network.add_host("sink")
    receiver = subprocess.Popen(
        host.command(sys.executable, "-c", ECHO, host.address, "9999", "2"),
        stdout=subprocess.PIPE,
        text=True,
    )
    assert receiver.stdout is not None
    assert receiver.stdout.readline() == "ready\n"
    sent = 2000
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.sendto(b"", (host.address, 9))  # the host's address resolved before the loss
        time.sleep(0.5)
        host.impair(loss=0.3)
        for _ in range(sent):
            sender.sendto(b"x", (host.address, 9999))
            time.sleep(0.0002)
    out, _ = receiver.communicate(timeout=30)
    received = int(out)
    say(f"UDP: {received} of {sent} datagrams received with 30 % loss")
    assert 0.6 * sent < received < 0.8 * sent


def _reaches(source: Host, url: str) -> bool:
    """Whether a GET of ``url`` from inside ``source`` answers within a second."""
    probe = f"import urllib.request; urllib.request.urlopen({url!r}, timeout=1.0)"
    done = subprocess.run(source.command(sys.executable, "-c", probe), capture_output=True)
    return done.returncode == 0


def test_a_partition_cuts_two_hosts_from_each_other_alone(network, tmp_path):
    client, server, other = (network.add_host(name) for name in ("client", "db", "other"))
    with http_server(server, tmp_path) as url:
        page = f"{url}/demo.yaml"
        assert _reaches(client, page)
        client.partition(server)
        assert not _reaches(client, page)
        assert _reaches(other, page)
        client.rejoin(server)
        assert _reaches(client, page)


def test_closing_the_network_leaves_nothing_behind(namespaces):
    addressing = Addressing.from_env()
    prefix = addressing.prefix
    with Network(addressing) as net:
        net.add_host("a")
        net.add_host("b")
        assert sum(1 for n in _namespaces() if n.startswith(f"{prefix}-")) == 2
    assert not [n for n in _namespaces() if n.startswith(f"{prefix}-")]
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    assert f": {prefix}b" not in links
    assert f": {addressing.bridge}" not in links


def _namespaces() -> list[str]:
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return [line.split()[0] for line in listed.splitlines() if line.strip()]
