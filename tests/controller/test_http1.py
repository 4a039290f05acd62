"""The controller's HTTP/1.1 transport on the wire: scripted answers from a raw TCP server
(chunked, closed, malformed, a kept-alive connection dropped) and the request bytes it writes.
The same transport against a real uvicorn replica is in ``test_transport.py``."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest

from services.controller.http1 import Http1Transport, request_bytes
from services.controller.http1 import _origin as origin_of
from services.controller.transport import StageRequest, TransportError

pytestmark = pytest.mark.anyio

OK = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nContent-Type: text/plain\r\n\r\nok"

# One connection's script: given the connection number and the request number on it, the bytes
# to answer (None: close the connection without answering; after an answer saying
# "Connection: close" the server closes it too).
Script = Callable[[int, int], bytes | None]


async def _read_request(reader: asyncio.StreamReader) -> bytes:
    head = await reader.readuntil(b"\r\n\r\n")
    length = 0
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            length = int(line.split(b":", 1)[1])
    return head + await reader.readexactly(length)


@asynccontextmanager
async def scripted(script: Script) -> AsyncIterator[tuple[str, list[bytes]]]:
    """A TCP server on loopback answering by ``script``; yields its URL and the requests seen."""
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
                if b"\r\nConnection: close\r\n" in answer:
                    return
        finally:
            writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}", seen
    finally:
        server.close()


async def test_writes_a_request_with_its_length_and_no_hop_headers():
    origin = origin_of("http://example.org:8001/renderer/")
    request = StageRequest.json("/render", b'{"a":1}', {"X-Request-ID": "abc", "Host": "evil"})
    data = request_bytes(origin, request)
    head, body = data.split(b"\r\n\r\n")
    lines = head.split(b"\r\n")
    assert lines[0] == b"POST /renderer/render HTTP/1.1"
    assert b"Host: example.org:8001" in lines
    assert b"Host: evil" not in lines
    assert b"Content-Length: 7" in lines
    assert b"X-Request-ID: abc" in lines
    assert body == b'{"a":1}'
    get = request_bytes(origin_of("http://[::1]"), StageRequest("GET", "/health"))
    assert get == b"GET /health HTTP/1.1\r\nHost: [::1]\r\n\r\n"


async def test_refuses_header_injection_and_non_http_urls():
    transport = Http1Transport(connect_timeout_s=1.0)
    with pytest.raises(ValueError, match="line break"):
        await transport.send(
            "http://127.0.0.1:9", StageRequest("GET", "/", headers={"X-Request-ID": "a\r\nB: c"}), 1
        )
    with pytest.raises(TransportError, match="not an http"):
        await transport.send("ftp://127.0.0.1", StageRequest("GET", "/"), 1.0)
    await transport.close()


async def test_keeps_one_connection_alive_and_reads_chunked_answers():
    chunked = (
        b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\nX-Thing: 1\r\n\r\n"
        b"3\r\nabc\r\n2\r\nde\r\n0\r\n\r\n"
    )

    def script(connection: int, turn: int) -> bytes:
        return chunked if turn == 1 else OK

    transport = Http1Transport(connect_timeout_s=1.0)
    async with scripted(script) as (url, seen):
        first = await transport.send(url, StageRequest("POST", "/a", b"x" * 1000), 5.0)
        second = await transport.send(url, StageRequest("GET", "/b"), 5.0)
        third = await transport.send(url, StageRequest("GET", "/c"), 5.0)
    await transport.close()
    assert (first.status_code, first.content, first.headers["content-type"]) == (
        200,
        b"ok",
        "text/plain",
    )
    assert (second.status_code, second.content, second.headers["x-thing"]) == (201, b"abcde", "1")
    assert third.content == b"ok"
    assert len(seen) == 3
    assert seen[0].endswith(b"x" * 1000)


async def test_a_kept_alive_connection_the_replica_dropped_is_replaced():
    # Connection 0 answers once, then closes when the second request arrives, without answering:
    # the race with a server's keep-alive timeout. The request goes again on a new connection.
    def script(connection: int, turn: int) -> bytes | None:
        return None if connection == 0 and turn == 1 else OK

    transport = Http1Transport(connect_timeout_s=1.0)
    async with scripted(script) as (url, seen):
        assert (await transport.send(url, StageRequest("GET", "/1"), 5.0)).content == b"ok"
        assert (await transport.send(url, StageRequest("GET", "/2"), 5.0)).content == b"ok"
        assert (await transport.send(url, StageRequest("GET", "/3"), 5.0)).content == b"ok"
    await transport.close()
    assert [r.split(b" ")[1] for r in seen] == [b"/1", b"/2", b"/2", b"/3"]


async def test_a_connection_closed_while_idle_is_not_tried_again():
    connections = 0

    async def answer_once(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal connections
        connections += 1
        await _read_request(reader)
        writer.write(OK)  # kept alive by its headers, then closed: a keep-alive timeout
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(answer_once, "127.0.0.1", 0)
    url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    transport = Http1Transport(connect_timeout_s=1.0)
    try:
        for _ in range(3):
            assert (await transport.send(url, StageRequest("GET", "/"), 5.0)).content == b"ok"
            await asyncio.sleep(0.05)
    finally:
        server.close()
        await transport.close()
    assert connections == 3


async def test_answers_framed_by_the_connection_closing():
    def script(connection: int, turn: int) -> bytes:
        return b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\nuntil the end"

    transport = Http1Transport(connect_timeout_s=1.0)
    async with scripted(script) as (url, _):
        for _ in range(2):  # the closed connection is not reused
            answer = await transport.send(url, StageRequest("GET", "/"), 5.0)
            assert answer.content == b"until the end"
    await transport.close()


@pytest.mark.parametrize(
    ("answer", "match"),
    [
        (b"NOT HTTP AT ALL\r\n\r\n", "malformed"),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nshort", "mid-answer"),
        (None, "without answering"),
    ],
    ids=["garbage", "truncated", "silent-close"],
)
async def test_broken_answers_are_transport_errors(answer, match):
    transport = Http1Transport(connect_timeout_s=1.0)

    async def close_after(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await _read_request(reader)
        if answer is not None:
            writer.write(answer)
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(close_after, "127.0.0.1", 0)
    url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    try:
        with pytest.raises(TransportError, match=match):
            await transport.send(url, StageRequest("GET", "/"), 5.0)
    finally:
        server.close()
        await transport.close()


async def test_times_out_and_does_not_reuse_the_connection():
    def script(connection: int, turn: int) -> bytes | None:
        return OK if connection == 1 else b""  # connection 0 never answers

    transport = Http1Transport(connect_timeout_s=1.0)
    async with scripted(script) as (url, _):
        with pytest.raises(TransportError, match="timed out"):
            await transport.send(url, StageRequest("GET", "/", timeout_s=0.2), 5.0)
        assert (await transport.send(url, StageRequest("GET", "/"), 5.0)).content == b"ok"
    await transport.close()


async def test_cancelled_exchange_closes_its_connection():
    def script(connection: int, turn: int) -> bytes | None:
        return OK if connection == 1 else b""

    transport = Http1Transport(connect_timeout_s=1.0)
    async with scripted(script) as (url, _):
        call = asyncio.create_task(transport.send(url, StageRequest("GET", "/"), 5.0))
        await asyncio.sleep(0.1)
        call.cancel()
        with pytest.raises(asyncio.CancelledError):
            await call
        # a late answer on the cancelled connection can never be taken for the next request's
        assert (await transport.send(url, StageRequest("GET", "/"), 5.0)).content == b"ok"
    await transport.close()
