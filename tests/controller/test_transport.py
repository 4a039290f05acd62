"""The controller's transport to its stages (aiohttp): real HTTP to a real replica process, and
scripted answers from a raw TCP server (chunked, closed, malformed, a kept-alive connection
dropped); its failures as :class:`TransportError`; the service token on every request."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest

from cosmos.launch import running_service
from services.common.auth import bearer
from services.controller.transport import (
    AiohttpTransport,
    StageAnswer,
    StageRequest,
    TransportError,
    WithServiceToken,
)

pytestmark = pytest.mark.anyio

OK = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nContent-Type: text/plain\r\n\r\nok"

# One connection's script: given the connection number and the request number on it, the bytes
# to answer (None: close the connection without answering).
Script = Callable[[int, int], bytes | None]


def _closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


async def _read_request(reader: asyncio.StreamReader) -> bytes:
    head = await reader.readuntil(b"\r\n\r\n")
    length = 0
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            length = int(line.split(b":", 1)[1])
    return head + await reader.readexactly(length)


@asynccontextmanager
async def scripted(
    script: Script, *, close_after: bool = False
) -> AsyncIterator[tuple[str, list[bytes]]]:
    """A TCP server on loopback answering by ``script`` (and closing the connection after each
    answer if ``close_after``); yields its URL and the requests seen."""
    seen: list[bytes] = []
    connections = 0

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal connections
        number, connections = connections, connections + 1
        try:
            for turn in range(100):
                try:
                    seen.append(await _read_request(reader))
                except (asyncio.IncompleteReadError, ConnectionError):
                    return
                answer = script(number, turn)
                if answer is None:
                    return
                writer.write(answer)
                await writer.drain()
                if close_after:
                    return
        finally:
            writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}", seen
    finally:
        server.close()


async def test_answers_refusals_and_timeouts(tmp_path):
    transport = AiohttpTransport(connect_timeout_s=2.0)
    try:
        with running_service(
            "tests.controller.fake_replica:app", tmp_path, {"FAKE_NAME": "x"}
        ) as replica:
            answer = await transport.send(replica.url, StageRequest("POST", "/work"), 5.0)
            assert answer.status_code == 200
            assert answer.json() == {"replica": "x"}
            assert answer.headers["content-type"] == "application/json"
            health = await transport.send(replica.url, StageRequest("GET", "/health"), 5.0)
            assert health.json()["status"] == "ok"
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
    transport = AiohttpTransport(connect_timeout_s=2.0)
    ports = set()
    env = {"FAKE_NAME": "x", "UVICORN_TIMEOUT_KEEP_ALIVE": "1"}
    try:
        with running_service("tests.controller.fake_replica:app", tmp_path, env) as replica:
            for pause_s in (0.0, 1.5, 0.95, 1.05, 1.0):
                await asyncio.sleep(pause_s)
                answer = await transport.send(replica.url, StageRequest("POST", "/work"), 5.0)
                assert answer.status_code == 200
                assert answer.json() == {"replica": "x"}
                ports.add(answer.headers["x-client-port"])
    finally:
        await transport.close()
    assert len(ports) >= 2  # the replica did close idle connections under the test


async def test_a_post_on_a_kept_alive_connection_the_replica_dropped_is_sent_again():
    # Connection 0 answers once, then closes when the second request arrives, without answering:
    # the race with a server's keep-alive timeout. Stage calls are POSTs, which aiohttp itself
    # would not send again.
    def script(connection: int, turn: int) -> bytes | None:
        return None if connection == 0 and turn == 1 else OK

    transport = AiohttpTransport(connect_timeout_s=1.0)
    async with scripted(script) as (url, seen):
        for path in ("/1", "/2", "/3"):
            answer = await transport.send(url, StageRequest.json(path, b"{}", {}), 5.0)
            assert answer.content == b"ok"
    await transport.close()
    assert [r.split(b" ")[1] for r in seen] == [b"/1", b"/2", b"/2", b"/3"]


async def test_reads_chunked_answers_on_one_kept_alive_connection():
    chunked = (
        b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\nX-Thing: 1\r\n\r\n"
        b"3\r\nabc\r\n2\r\nde\r\n0\r\n\r\n"
    )
    transport = AiohttpTransport(connect_timeout_s=1.0)
    async with scripted(lambda connection, turn: chunked if turn == 1 else OK) as (url, seen):
        first = await transport.send(url, StageRequest("POST", "/a", b"x" * 1000), 5.0)
        second = await transport.send(url, StageRequest("GET", "/b"), 5.0)
    await transport.close()
    assert (first.status_code, first.content) == (200, b"ok")
    assert (second.status_code, second.content, second.headers["x-thing"]) == (201, b"abcde", "1")
    assert seen[0].endswith(b"x" * 1000)


@pytest.mark.parametrize(
    ("answer", "sent"),
    [
        (b"NOT HTTP AT ALL\r\n\r\n", 1),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nshort", 1),
        (None, 2),  # closed unanswered: sent once more, then an error
    ],
    ids=["garbage", "truncated", "silent-close"],
)
async def test_broken_answers_are_transport_errors(answer, sent):
    async with scripted(lambda connection, turn: answer, close_after=True) as (url, seen):
        transport = AiohttpTransport(connect_timeout_s=1.0)
        try:
            with pytest.raises(TransportError):
                await transport.send(url, StageRequest.json("/", b"{}", {}), 5.0)
        finally:
            await transport.close()
    assert len(seen) == sent


class Recording:
    """A transport that answers 200 and keeps what it was sent."""

    def __init__(self) -> None:
        self.sent: list[StageRequest] = []

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        self.sent.append(request)
        return StageAnswer(200, b"")

    async def close(self) -> None:
        pass


async def test_every_stage_call_carries_the_token():
    inner = Recording()
    transport = WithServiceToken(inner, "t" * 32)
    await transport.send("http://r1", StageRequest("GET", "/x", headers={"X-Request-ID": "7"}), 1)
    assert dict(inner.sent[-1].headers) == {"X-Request-ID": "7", **bearer("t" * 32)}
    await WithServiceToken(inner, None).send("http://r1", StageRequest("GET", "/x"), 1)
    assert dict(inner.sent[-1].headers) == {}  # COSMOS_SERVICE_AUTH=off: nothing to send


async def test_a_timeout_noticed_late_says_the_loop_was_busy_not_the_replica():
    """A replica that answers nothing: its timeout, on an idle loop, fires on time; on a loop
    that was blocked past it (a stall of the controller's own), it fires late, and says so."""
    transport = AiohttpTransport(connect_timeout_s=2.0)
    try:
        async with scripted(lambda _, __: b"") as (url, _):  # reads, never answers
            request = StageRequest("POST", "/work", b"x", timeout_s=0.2)
            with pytest.raises(TransportError) as on_time:
                await transport.send(url, request, 60.0)
            assert on_time.value.late_s < 0.1
            assert not on_time.value.loop_was_late
            call = asyncio.create_task(transport.send(url, request, 60.0))
            await asyncio.sleep(0.05)  # sent; now the loop is blocked past the 0.2 s
            time.sleep(1.0)
            with pytest.raises(TransportError) as late:
                await call
            assert late.value.late_s > 0.6
            assert late.value.loop_was_late
    finally:
        await transport.close()
