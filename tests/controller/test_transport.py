"""The controller's transports to its stages (HTTP/1.1 of its own for ``http://``, aiohttp for
``https://``): real HTTP to a real replica process, its failures as :class:`TransportError`."""

from __future__ import annotations

import asyncio
import socket

import pytest

from services.common.launch import running_service
from services.controller.http1 import Http1Transport
from services.controller.transport import (
    AiohttpTransport,
    StageRequest,
    Transport,
    TransportError,
)

pytestmark = pytest.mark.anyio


def _closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.mark.parametrize("kind", [Http1Transport, AiohttpTransport])
async def test_answers_refusals_and_timeouts(tmp_path, kind):
    transport: Transport = kind(connect_timeout_s=2.0)
    try:
        with running_service(
            "tests.controller.fake_replica:app", tmp_path, {"FAKE_NAME": "x"}
        ) as replica:
            answer = await transport.send(replica.url, StageRequest("POST", "/work"), 5.0)
            assert answer.status_code == 200
            assert answer.json() == {"replica": "x"}
            assert answer.headers["content-type"] == "application/json"
            health = await transport.send(replica.url, StageRequest("GET", "/health"), 5.0)
            assert health.json()["status"] == "ok"  # the same kept-alive connection
            missing = await transport.send(replica.url, StageRequest("GET", "/nope"), 5.0)
            assert missing.status_code == 404  # an answer, not a transport error
        with pytest.raises(TransportError):
            await transport.send(
                f"http://127.0.0.1:{_closed_port()}", StageRequest("GET", "/"), 5.0
            )
        with running_service(
            "tests.controller.fake_replica:app", tmp_path, {"FAKE_FAIL": "hang"}
        ) as stuck:
            with pytest.raises(TransportError, match="timed out"):
                await transport.send(stuck.url, StageRequest("POST", "/work", timeout_s=0.3), 60.0)
            stuck.process.kill()  # it would wait for its hanging task on a graceful stop
    finally:
        await transport.close()


async def test_survives_the_replicas_keep_alive_timeout(tmp_path):
    """uvicorn closes a connection idle for its keep-alive timeout; the next call, made just as
    or after it closes, is answered on a new connection and never seen as a failure."""
    transport = Http1Transport(connect_timeout_s=2.0)
    connect = transport._connect
    connects = 0

    async def counted(origin):
        nonlocal connects
        connects += 1
        return await connect(origin)

    transport._connect = counted  # type: ignore[method-assign]
    env = {"FAKE_NAME": "x", "UVICORN_TIMEOUT_KEEP_ALIVE": "1"}
    try:
        with running_service("tests.controller.fake_replica:app", tmp_path, env) as replica:
            for pause_s in (0.0, 1.5, 0.95, 1.05, 1.0):
                await asyncio.sleep(pause_s)
                answer = await transport.send(replica.url, StageRequest("POST", "/work"), 5.0)
                assert answer.status_code == 200
                assert answer.json() == {"replica": "x"}
    finally:
        await transport.close()
    assert connects >= 2  # the replica did close idle connections under the test
