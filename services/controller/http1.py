"""Keep-alive HTTP/1.1 to the stages, straight over asyncio with the httptools response parser.

The controller's calls to its stages are small and regular: a request with a known length to a
replica it talks to all the time, answered with ``Content-Length`` (or chunked). A general
client's machinery for that is most of a hop's cost on a machine whose processes wake up cold
after waiting out a render: a round trip to a bare ASGI app after a 100 ms pause took 1.7 ms
through aiohttp and 0.9 ms written out like this (this machine, one run). The answer is parsed
by httptools, the parser uvicorn uses, so chunked bodies, keep-alive and malformed answers are
handled by well-tested code; this module only writes requests and keeps connections.

Every stage call is a pure function of its request (render, detect, plan), so a request that
met a kept-alive connection the replica had just closed, before any byte of an answer, is sent
again on another idle connection or a new one (a new one that closes unanswered is an error).
Anything else that goes wrong is a :class:`TransportError` for the broker.
``https://`` URLs go through :class:`~services.controller.transport.AiohttpTransport`.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import cast
from urllib.parse import urlsplit

import httptools

from services.controller.transport import (
    AiohttpTransport,
    StageAnswer,
    StageRequest,
    TransportError,
)

__all__ = ["Http1Transport"]


@dataclass(frozen=True)
class _Origin:
    host: str
    port: int
    prefix: str  # the base URL's path, without its trailing slash
    authority: bytes  # the Host header


def _origin(base_url: str) -> _Origin:
    parts = urlsplit(base_url)
    if parts.scheme != "http" or not parts.hostname:
        raise TransportError(f"not an http:// URL: {base_url!r}")
    try:
        port = parts.port or 80
    except ValueError as exc:
        raise TransportError(f"bad port in {base_url!r}") from exc
    host = parts.hostname
    authority = f"[{host}]" if ":" in host else host
    if parts.port is not None:
        authority += f":{parts.port}"
    return _Origin(host, port, parts.path.rstrip("/"), authority.encode("ascii"))


def _header_bytes(text: str, what: str) -> bytes:
    if "\r" in text or "\n" in text or "\0" in text:
        raise ValueError(f"{what} holds a line break: {text!r}")
    return text.encode("latin-1")


def request_bytes(origin: _Origin, request: StageRequest) -> bytes:
    """``request`` as it goes on the wire (``Content-Length`` always, never chunked)."""
    target = _header_bytes(origin.prefix + request.path, "path")
    lines = [
        _header_bytes(request.method, "method") + b" " + target + b" HTTP/1.1",
        b"Host: " + origin.authority,
    ]
    for name, value in request.headers.items():
        if name.lower() not in ("host", "content-length", "transfer-encoding", "connection"):
            lines.append(_header_bytes(name, "header name") + b": " + _header_bytes(value, name))
    body = request.body or b""
    if body or request.method not in ("GET", "HEAD", "DELETE"):
        lines.append(b"Content-Length: %d" % len(body))
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


class _Stale(Exception):
    """A kept-alive connection was closed before any byte of the answer came."""


class _Connection(asyncio.Protocol):
    """One kept-alive connection: one exchange at a time."""

    def __init__(self) -> None:
        self._transport: asyncio.Transport | None = None
        # One parser for the connection's answers in turn; after a parse error it is closed.
        self._parser = httptools.HttpResponseParser(self)
        self._answer: asyncio.Future[StageAnswer] | None = None
        self._headers: dict[str, str] = {}
        self._body: list[bytes] = []
        self._got_bytes = False
        self._headers_done = False
        self.closed = False
        self.reusable = False

    # -- asyncio.Protocol ---------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        self._got_bytes = True
        if self._answer is None or self._answer.done():
            self.close()  # bytes nobody asked for: this connection is out of step
            return
        try:
            self._parser.feed_data(data)
        except httptools.HttpParserUpgrade:
            self._fail(TransportError("the replica answered with a protocol upgrade"))
        except httptools.HttpParserError as exc:
            self._fail(TransportError(f"malformed HTTP answer: {exc}"))

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self.reusable = False
        if self._answer is None or self._answer.done():
            return
        if not self._got_bytes:
            self._answer.set_exception(_Stale())
        elif self._headers_done and not self._framed():
            self._complete()  # an answer delimited by the end of the connection
        else:
            self._answer.set_exception(
                TransportError(f"the replica closed the connection mid-answer ({exc or 'EOF'})")
            )

    # -- httptools callbacks ------------------------------------------------------------------

    def on_header(self, name: bytes, value: bytes) -> None:
        self._headers[name.decode("latin-1").lower()] = value.decode("latin-1")

    def on_headers_complete(self) -> None:
        self._headers_done = True

    def on_body(self, body: bytes) -> None:
        self._body.append(body)

    def on_message_complete(self) -> None:
        self._complete()

    # -- exchanges ----------------------------------------------------------------------------

    def _framed(self) -> bool:
        return "content-length" in self._headers or "transfer-encoding" in self._headers

    def _complete(self) -> None:
        if self._answer is None or self._answer.done():
            return
        status = self._parser.get_status_code()
        if status < 200:  # 1xx: the real answer follows
            self._headers, self._body, self._headers_done = {}, [], False
            return
        self.reusable = not self.closed and self._parser.should_keep_alive()
        self._answer.set_result(StageAnswer(status, b"".join(self._body), self._headers))

    def _fail(self, exc: Exception) -> None:
        if self._answer is not None and not self._answer.done():
            self._answer.set_exception(exc)
        self.close()

    async def exchange(self, data: bytes) -> StageAnswer:
        """Send one request and wait for its whole answer."""
        if self.closed or self._transport is None:
            raise _Stale()
        self._answer = asyncio.get_running_loop().create_future()
        self._headers, self._body = {}, []
        self._got_bytes = self._headers_done = self.reusable = False
        self._transport.write(data)
        return await self._answer

    def close(self) -> None:
        self.closed = True
        self.reusable = False
        if self._transport is not None:
            self._transport.close()


class Http1Transport:
    """The broker's transport: kept-alive connections per replica, one request at a time on each.

    ``https://`` replicas are served by an :class:`AiohttpTransport` made on first use.
    """

    def __init__(self, connect_timeout_s: float) -> None:
        self.connect_timeout_s = connect_timeout_s
        self._origins: dict[str, _Origin] = {}
        self._idle: dict[tuple[str, int], list[_Connection]] = {}
        self._tls: AiohttpTransport | None = None

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        if base_url.startswith("https://"):
            if self._tls is None:
                self._tls = AiohttpTransport(self.connect_timeout_s)
            return await self._tls.send(base_url, request, timeout_s)
        origin = self._origins.get(base_url)
        if origin is None:
            origin = self._origins[base_url] = _origin(base_url)
        data = request_bytes(origin, request)
        total_s = request.timeout_s or timeout_s
        try:
            async with asyncio.timeout(total_s):
                return await self._exchange(origin, data)
        except TimeoutError as exc:
            raise TransportError(f"timed out ({total_s:g} s)") from exc

    async def _exchange(self, origin: _Origin, data: bytes) -> StageAnswer:
        key = (origin.host, origin.port)
        idle = self._idle.setdefault(key, [])
        while idle:
            connection = idle.pop()
            if connection.closed:
                continue
            try:
                return await self._use(connection, idle, data)
            except _Stale:
                continue  # the replica closed it while it was idle: another, or a new one
        connection = await self._connect(origin)
        try:
            return await self._use(connection, idle, data)
        except _Stale as exc:
            raise TransportError("the replica closed a new connection without answering") from exc

    async def _use(
        self, connection: _Connection, idle: list[_Connection], data: bytes
    ) -> StageAnswer:
        try:
            answer = await connection.exchange(data)
        except BaseException:
            connection.close()  # cancelled or failed mid-exchange: its state is unknown
            raise
        if connection.reusable:
            idle.append(connection)
        else:
            connection.close()
        return answer

    async def _connect(self, origin: _Origin) -> _Connection:
        loop = asyncio.get_running_loop()
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                _, connection = await loop.create_connection(_Connection, origin.host, origin.port)
        except TimeoutError as exc:
            raise TransportError(
                f"connect to {origin.host}:{origin.port} timed out ({self.connect_timeout_s:g} s)"
            ) from exc
        except OSError as exc:
            raise TransportError(f"{type(exc).__name__}: {exc}") from exc
        return connection

    async def close(self) -> None:
        for connections in self._idle.values():
            for connection in connections:
                connection.close()
        self._idle.clear()
        if self._tls is not None:
            with contextlib.suppress(Exception):
                await self._tls.close()
            self._tls = None
