"""How the controller's broker sends one request to one replica: plain data in, plain data out.

A :class:`StageRequest` is bytes and headers, so the broker can send it again to another replica;
a :class:`StageAnswer` is the status, headers and the whole body. The broker's transport is
:class:`AiohttpTransport`: one aiohttp session with keep-alive connections to every replica,
``http://`` or ``https://``. Tests inject other transports (in-process apps, scripted faults).

:class:`WithServiceToken` wraps any transport to send the stack's service token (``Authorization:
Bearer``) with every request: the stages serve no one else (:mod:`services.common.auth`).

A hand-written HTTP/1.1 client (asyncio and httptools) served ``http://`` replicas until it was
measured against this one (``git show 5a86024:benchmarks/transport.py``): it saved ~0.45 ms a
stage call, ~2 ms (~1 %) of a search, within noise; not worth ~500 lines of protocol code.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import aiohttp
from urllib3 import encode_multipart_formdata

from services.common.auth import bearer

__all__ = [
    "LATE_S",
    "AiohttpTransport",
    "StageAnswer",
    "StageRequest",
    "Transport",
    "TransportError",
    "WithServiceToken",
]


@dataclass(frozen=True)
class StageRequest:
    """One HTTP request to a replica, relative to its base URL."""

    method: str
    path: str
    body: bytes | None = None
    headers: Mapping[str, str] = field(default_factory=dict)
    timeout_s: float | None = None  # None: the stage's timeout

    @classmethod
    def json(cls, path: str, body: str | bytes, headers: Mapping[str, str]) -> StageRequest:
        """``POST path`` with a JSON document."""
        data = body.encode() if isinstance(body, str) else body
        return cls("POST", path, data, {**headers, "Content-Type": "application/json"})

    @classmethod
    def form(
        cls,
        path: str,
        parts: Sequence[tuple[str, str, bytes]],
        headers: Mapping[str, str],
    ) -> StageRequest:
        """``POST path`` with a ``multipart/form-data`` body of ``parts`` (name, media type,
        bytes; a part of media type ``text/plain`` is a text field, any other a file named as
        its field), encoded by urllib3 with a fresh random boundary (RFC 7578)."""
        fields: list[tuple[str, str | bytes | tuple[str, bytes, str]]] = [
            (name, data) if media_type == "text/plain" else (name, (name, data, media_type))
            for name, media_type, data in parts
        ]
        body, content_type = encode_multipart_formdata(fields)
        return cls("POST", path, body, {**headers, "Content-Type": content_type})


@dataclass(frozen=True)
class StageAnswer:
    """A replica's whole answer (header names in lower case)."""

    status_code: int
    content: bytes
    headers: Mapping[str, str] = field(default_factory=dict)

    def json(self) -> Any:
        return json.loads(self.content)

    @property
    def text(self) -> str:
        return self.content.decode(errors="replace")


class TransportError(Exception):
    """The request got no answer: refused, reset, timed out or not HTTP.

    ``late_s``: how long after it was due a timeout was noticed. An event loop busy elsewhere
    (a stall of the controller's own) notices a timer late, and meanwhile a connection that
    the replica accepted at once waits unread, so a timeout noticed seconds late says nothing
    of the replica (:attr:`loop_was_late`).
    """

    def __init__(self, message: str, *, late_s: float = 0.0) -> None:
        super().__init__(message)
        self.late_s = late_s

    @property
    def loop_was_late(self) -> bool:
        """Whether the timeout fired :data:`LATE_S` or more after it was due."""
        return self.late_s >= LATE_S


LATE_S = 0.5
"""A timeout noticed this late (seconds) is the caller's loop's, not the replica's: a timer on
an idle loop fires within milliseconds of its time."""


class Transport(Protocol):
    """Sends a request to the replica at ``base_url``."""

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer: ...

    async def close(self) -> None: ...


class AiohttpTransport:
    """Keep-alive HTTP/1.1 (or TLS) over one aiohttp session (made on first use, in the loop).

    Every stage call is a pure function of its request (render, detect, plan), so a request
    whose connection the replica closed before answering (most often a kept-alive connection
    that met the replica's keep-alive timeout just as it was reused) is sent once more. aiohttp
    does that itself only for idempotent methods, and stage calls are ``POST``. Anything else
    that goes wrong is a :class:`TransportError` for the broker.
    """

    def __init__(self, connect_timeout_s: float) -> None:
        self.connect_timeout_s = connect_timeout_s
        self._session: aiohttp.ClientSession | None = None

    def _client(self) -> aiohttp.ClientSession:
        if self._session is None or self._session.closed:
            self._session = aiohttp.ClientSession(
                connector=aiohttp.TCPConnector(limit=0, ttl_dns_cache=10),
                auto_decompress=False,
                raise_for_status=False,
            )
        return self._session

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        total_s = request.timeout_s or timeout_s
        deadline = attempt = time.monotonic()
        deadline += total_s
        try:
            try:
                return await self._send(base_url, request, total_s)
            except aiohttp.ClientConnectorError:
                raise  # not connected at all: nothing was sent
            except (aiohttp.ServerDisconnectedError, aiohttp.ClientOSError):
                # closed unanswered: once more, in the time that is left
                attempt = time.monotonic()
                return await self._send(base_url, request, deadline - attempt)
        except TimeoutError as exc:  # before ClientError: aiohttp's timeouts are both
            connecting = isinstance(exc, aiohttp.ConnectionTimeoutError)
            due = attempt + self.connect_timeout_s if connecting else deadline
            raise TransportError(
                f"timed out ({type(exc).__name__}, {total_s:g} s)",
                late_s=max(0.0, time.monotonic() - due),
            ) from exc
        except aiohttp.ClientError as exc:
            raise TransportError(f"{type(exc).__name__}: {exc}") from exc

    async def _send(self, base_url: str, request: StageRequest, total_s: float) -> StageAnswer:
        if total_s <= 0:
            raise TimeoutError("no time left")
        timeout = aiohttp.ClientTimeout(total=total_s, connect=self.connect_timeout_s)
        async with self._client().request(
            request.method,
            base_url + request.path,
            data=request.body,
            headers=dict(request.headers),
            timeout=timeout,
            allow_redirects=False,
        ) as response:
            content = await response.read()
            headers = {name.lower(): value for name, value in response.headers.items()}
            return StageAnswer(response.status, content, headers)

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()
            self._session = None


class WithServiceToken:
    """``inner``, sending ``token`` as ``Authorization: Bearer`` with every request (nothing
    added when ``token`` is None: the stages ask for none)."""

    def __init__(self, inner: Transport, token: str | None) -> None:
        self.inner = inner
        self._headers = bearer(token)

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        if self._headers:
            request = replace(request, headers={**request.headers, **self._headers})
        return await self.inner.send(base_url, request, timeout_s)

    async def close(self) -> None:
        await self.inner.close()
