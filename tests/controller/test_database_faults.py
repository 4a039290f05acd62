"""The controller's database failing: one that cannot be used stops the controller's start-up
with one line naming the setting (a real process, no traceback); one that goes away while it runs
makes ``/readyz`` fail and requests answer 503, until it is back; one that hangs holds the
requests that need it, never the probes (the store is called off the event loop)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import psycopg
import pytest

from cosmos.launch import free_port
from services.controller.readiness import PROBE_TIMEOUT_S
from tests.controller.test_quotas import submit
from tests.hosts.network import Relay

ROOT = Path(__file__).resolve().parents[2]
HUNG_S = 3.0  # each way: what the database's answers are held back while it hangs


def _start(database_url: str, port: int) -> subprocess.Popen[str]:
    env = {**os.environ, "COSMOS_CONTROLLER_DATABASE_URL": database_url}
    command = [sys.executable, "-m", "services.common.server", "services.controller.app:app"]
    return subprocess.Popen(
        [*command, "--port", str(port)],
        env=env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def test_a_database_that_cannot_be_used_fails_start_up_in_one_line(postgres):
    closed = 18699 if postgres.port != 18699 else 18697
    cases = [
        (
            postgres.url(password="wrong-password"),
            ("PostgreSQL at 127.0.0.1:", "password authentication failed"),
        ),
        (
            f"postgresql://cosmos:x@127.0.0.1:{closed}/cosmos",
            ("PostgreSQL at 127.0.0.1:", "Connection refused"),
        ),
        (
            "mysql://cosmos@db/cosmos",
            ("must look like sqlite:///path/to/file.db or postgresql://",),
        ),
    ]
    started = [(_start(url, 18695 + n), why) for n, (url, why) in enumerate(cases)]  # at once
    for process, whys in started:
        output, _ = process.communicate(timeout=120)
        assert process.returncode != 0, output
        lines = [line for line in output.splitlines() if "COSMOS_CONTROLLER_DATABASE_URL" in line]
        assert len(lines) == 1, output
        assert all(why in lines[0] for why in whys), lines[0]
        assert "Traceback" not in output
        assert "wrong-password" not in output


def allow_connections(postgres, database: str, allowed: bool) -> None:
    with psycopg.connect(postgres.url(), autocommit=True) as admin:
        admin.execute(f'ALTER DATABASE "{database}" ALLOW_CONNECTIONS {str(allowed).lower()}')
        if not allowed:
            admin.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s",
                (database,),
            )


@pytest.mark.anyio
async def test_a_database_that_goes_away_makes_the_controller_unready_and_refuse(
    postgres, start_controller
):
    url = postgres.new_database()
    database = url.rsplit("/", 1)[1]
    async with start_controller(controller_database_url=url) as (_, client):
        assert (await client.get("/searches")).status_code == 200
        allow_connections(postgres, database, allowed=False)
        try:
            ready = await client.get("/readyz")
            assert ready.status_code == 503
            assert "the search database does not answer" in ready.json()["reasons"]
            for response in (await submit(client), await client.get("/searches")):
                assert response.status_code == 503, response.text
                assert response.headers["content-type"] == "application/problem+json"
                assert response.json()["type"] == "urn:cosmos:problem:database-unavailable"
                assert int(response.headers["retry-after"]) >= 1
                assert "127.0.0.1" not in response.text
        finally:
            allow_connections(postgres, database, allowed=True)
        assert (await client.get("/searches")).status_code == 200  # back: the pool reconnects
        ready = await client.get("/readyz")
        assert "the search database does not answer" not in ready.json()["reasons"]


@pytest.mark.anyio
async def test_a_database_that_hangs_holds_no_probe(postgres, start_controller):
    """The database stops answering (its traffic held back by a relay, as over a dead path): a
    request that needs it waits, but ``/livez`` answers at once and ``/readyz`` says no within
    its probe timeout; once the database answers again, so does the request."""
    port = free_port()
    relay = Relay(
        subprocess.Popen(
            [sys.executable, "-m", "tests.hosts.relay", f"127.0.0.1:{port}", str(postgres.port)],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        ),
        ("127.0.0.1", port),
        postgres.port,
    )
    assert relay.process.stdout is not None
    assert relay.process.stdout.readline().strip() == "ready"
    url = postgres.new_database().replace(f":{postgres.port}/", f":{port}/")
    try:
        async with start_controller(controller_database_url=url) as (_, client):
            assert (await client.get("/searches")).status_code == 200
            relay.set_delay(HUNG_S * 1000)
            waiting = asyncio.create_task(client.get("/searches"))
            await asyncio.sleep(0.3)  # its store call waits for the database
            t0 = time.perf_counter()
            live = await client.get("/livez")
            live_s = time.perf_counter() - t0
            ready = await client.get("/readyz")
            ready_s = time.perf_counter() - t0 - live_s
            assert not waiting.done()
            relay.set_delay(0.0)
            assert (await waiting).status_code == 200
    finally:
        relay.stop()
    assert live.status_code == 200
    assert live_s < 0.5
    assert ready.status_code == 503
    assert "the search database does not answer" in ready.json()["reasons"]
    assert ready_s < PROBE_TIMEOUT_S + 0.5
