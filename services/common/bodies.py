"""Request bodies: a size limit, a per-process budget of the bytes in flight, and a deadline.

One pure-ASGI middleware (:class:`BodyMiddleware`) reads every request body before the app runs,
so that what the app is given is bounded three ways:

* **size**: a body over ``max_bytes`` gets 413, by its ``Content-Length`` before anything is read,
  or by counting a streamed (chunked) one. FastAPI has no limit of its own, and an error while
  the app reads the body would be a 400 there.
* **bytes in flight** (:class:`BodyBudget`): a request is admitted by its declared length before
  its body is read, and holds those bytes until the app has answered it (the app keeps the body,
  and what it makes of it, that long). When they do not fit, it waits, first come first served,
  for at most ``wait_s``; then it gets 503 with ``Retry-After`` and the connection is closed, its
  body never read. A chunked body, of unknown length, holds ``max_bytes`` while it streams and
  gives back what it did not use once it has arrived.
* **time**: the body must have arrived within ``timeout_s + size / min_bytes_per_s`` of its
  admission (``size`` the declared length, or ``max_bytes`` when chunked), else 408 and the
  connection is closed; its bytes are given back at once. A trickling client holds a budget's
  share no longer than that.

Small bodies do not wait behind large ones: a body of at most ``small_bytes`` (1/16 of the size
limit: a JSON request, a search view's 230 KB PPM, a typical target) is counted in a lane of its
own, ``limit_bytes / 4``, so a flood of maximal uploads fills the large lane and leaves it free.
Requests without a body (``GET``) are passed through untouched. The memory bodies may hold at
once is thus ``1.25 · limit_bytes``, each body once (twice while the app turns it into ``bytes``;
then the copy read here is dropped).

Credentials are checked before any of this, from the request's head: the stages' service token
(:mod:`services.common.auth`) and the controller's API keys (:mod:`services.controller.auth`)
refuse a stranger's request before its body is admitted or read.

With the defaults (:meth:`BodyLimits.for_limit`), ``limit_bytes`` is four maximal bodies: for a
48 MiB upload limit, 192 MiB of large bodies and a 48 MiB lane of bodies up to 3 MiB.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from dataclasses import dataclass
from typing import Final

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.common.byte_budget import ByteBudget
from services.common.errors import (
    PayloadTooLargeError,
    ProblemDetails,
    ServiceUnavailableError,
    problem_type,
)

__all__ = [
    "DEFAULT_BODY_TIMEOUT_S",
    "DEFAULT_BODY_WAIT_S",
    "DEFAULT_MIN_BYTES_PER_S",
    "BodyBudget",
    "BodyLimits",
    "BodyMiddleware",
    "Hold",
    "declared_length",
    "has_body",
    "send_problem",
]

DEFAULT_BODY_TIMEOUT_S: Final = 10.0
"""Seconds any body has to arrive, on top of its size's share (a LAN sends 20 MB in 0.2 s)."""
DEFAULT_MIN_BYTES_PER_S: Final = 512 * 1024
"""The slowest upload served in full: 4 Mbit/s, so a 20 MiB body may take 40 s more."""
DEFAULT_BODY_WAIT_S: Final = 5.0
"""Seconds a request waits for its bytes before a 503 (a maximal upload is handled in ~0.1-1 s)."""
BUDGET_BODIES: Final = 4
"""Maximal bodies the default budget holds at once."""
SMALL_FRACTION: Final = 16
"""A body of at most ``max_bytes / SMALL_FRACTION`` is small."""
SMALL_LANE_FRACTION: Final = 4
"""The small bodies' lane is ``limit_bytes / SMALL_LANE_FRACTION``."""

_log = logging.getLogger("cosmos.http")


@dataclass(frozen=True)
class BodyLimits:
    """How a service bounds request bodies (see the module's docstring).

    ``budget_bytes`` None: no budget (only the size limit and the deadline apply).
    """

    max_bytes: int
    budget_bytes: int | None = None
    wait_s: float = DEFAULT_BODY_WAIT_S
    timeout_s: float = DEFAULT_BODY_TIMEOUT_S
    min_bytes_per_s: float = DEFAULT_MIN_BYTES_PER_S

    def __post_init__(self) -> None:
        if self.max_bytes < 1:
            raise ValueError("max_bytes must be positive")
        if self.budget_bytes is not None and self.budget_bytes < self.max_bytes:
            raise ValueError(
                f"a body budget of {self.budget_bytes} bytes cannot hold one body of the "
                f"{self.max_bytes} bytes allowed"
            )
        if self.wait_s < 0 or not self.timeout_s > 0 or not self.min_bytes_per_s > 0:
            raise ValueError("wait_s must not be negative, timeout_s and min_bytes_per_s positive")

    @classmethod
    def for_limit(
        cls,
        max_bytes: int,
        *,
        budget_bytes: int | None = None,
        wait_s: float = DEFAULT_BODY_WAIT_S,
        timeout_s: float = DEFAULT_BODY_TIMEOUT_S,
        min_bytes_per_s: float = DEFAULT_MIN_BYTES_PER_S,
    ) -> BodyLimits:
        """Limits with a budget: ``budget_bytes``, or :data:`BUDGET_BODIES` maximal bodies."""
        return cls(
            max_bytes,
            budget_bytes if budget_bytes is not None else BUDGET_BODIES * max_bytes,
            wait_s,
            timeout_s,
            min_bytes_per_s,
        )

    @property
    def small_bytes(self) -> int:
        """The largest body counted in the small bodies' lane."""
        return self.max_bytes // SMALL_FRACTION

    def deadline_s(self, size: int | None) -> float:
        """Seconds a body of ``size`` bytes (None: streamed, so at most ``max_bytes``) has to
        arrive: ``timeout_s + size / min_bytes_per_s``."""
        return self.timeout_s + (self.max_bytes if size is None else size) / self.min_bytes_per_s

    def budget(self) -> BodyBudget | None:
        """A budget of these limits (None without one)."""
        if self.budget_bytes is None:
            return None
        return BodyBudget(self.budget_bytes, self.small_bytes, self.wait_s)


class BodyBudget:
    """Request-body bytes in flight in one process: ``limit_bytes`` for large bodies and a lane
    of ``limit_bytes / 4`` for bodies of at most ``small_bytes``, each first come first served;
    a request waits up to ``wait_s`` for its bytes."""

    def __init__(self, limit_bytes: int, small_bytes: int, wait_s: float) -> None:
        if limit_bytes < 1 or small_bytes < 0 or wait_s < 0:
            raise ValueError("limit_bytes must be positive, small_bytes and wait_s not negative")
        self.small_bytes = small_bytes
        self.wait_s = wait_s
        self._large = ByteBudget(limit_bytes)
        self._small = ByteBudget(max(small_bytes, limit_bytes // SMALL_LANE_FRACTION))

    @property
    def limit_bytes(self) -> int:
        return self._large.limit_bytes

    @property
    def in_use(self) -> int:
        """Bytes held now, in both lanes."""
        return self._large.in_use + self._small.in_use

    @property
    def peak(self) -> int:
        """The most bytes the large lane held at once, plus the small lane's most."""
        return self._large.peak + self._small.peak

    @property
    def waiting(self) -> int:
        """Requests waiting for their bytes."""
        return self._large.waiting + self._small.waiting

    async def acquire(self, size: int) -> Hold | None:
        """Hold ``size`` bytes; None if they did not fit within ``wait_s``."""
        lane = self._small if size <= self.small_bytes else self._large
        if not await lane.acquire(size, self.wait_s):
            return None
        return Hold(lane, size)


class Hold:
    """Bytes a request holds in a :class:`BodyBudget`, until :meth:`release`."""

    def __init__(self, lane: ByteBudget, size: int) -> None:
        self._lane = lane
        self.size = size

    def shrink(self, size: int) -> None:
        """Give back what the body did not use: it has ``size`` bytes, not :attr:`size`."""
        if 0 <= size < self.size:
            self._lane.release(self.size - size)
            self.size = size

    def release(self) -> None:
        """Give back every byte held (once)."""
        self._lane.release(self.size)
        self.size = 0


def declared_length(scope: Scope) -> int | None:
    """The request's ``Content-Length`` (None when absent or not a number)."""
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


def _chunked(scope: Scope) -> bool:
    return any(
        name == b"transfer-encoding" and b"chunked" in value.lower()
        for name, value in scope.get("headers", [])
    )


def has_body(scope: Scope) -> bool:
    """Whether the request declares a body: a positive ``Content-Length``, or a chunked one."""
    declared = declared_length(scope)
    return bool(declared) or (declared is None and _chunked(scope))


async def send_problem(
    send: Send, scope: Scope, problem: ProblemDetails, headers: dict[str, str] | None = None
) -> None:
    """Send ``problem`` as problem+json and have the server close the connection after it (the
    body was not read, or not all of it)."""
    body = json.dumps(problem.model_dump(mode="json", exclude_none=True)).encode()
    extra = [(name.lower().encode(), value.encode()) for name, value in (headers or {}).items()]
    await send(
        {
            "type": "http.response.start",
            "status": problem.status,
            "headers": [
                (b"content-type", b"application/problem+json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
                *extra,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class _TooLarge(Exception):
    pass


class BodyMiddleware:
    """Bound every request body by size, by the process's bytes in flight, and by time
    (:class:`BodyLimits`; the module's docstring says how). The app gets the whole body in one
    ``http.request`` message (as a ``bytearray``, see :meth:`_read`)."""

    def __init__(self, app: ASGIApp, limits: BodyLimits) -> None:
        self.app = app
        self.limits = limits
        self.budget = limits.budget()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if not has_body(scope):  # nothing to bound
            await self.app(scope, receive, send)
            return
        declared = declared_length(scope)
        if declared is not None and declared > self.limits.max_bytes:
            await self._too_large(scope, send, f"the request body of {declared} bytes")
            return
        hold: Hold | None = None
        if self.budget is not None:
            size = self.limits.max_bytes if declared is None else declared
            hold = await self.budget.acquire(size)
            if hold is None:
                await self._busy(scope, send, self.budget, size)
                return
        try:
            body = await self._read(scope, receive, send, declared)
            if body is None:
                return  # answered (408, 413) or the client went away
            if hold is not None:
                hold.shrink(len(body))
            replay = _replay(body, receive)
            del body  # the app holds it from here; it is not kept alive here after the app
            await self.app(scope, replay, send)
        finally:
            if hold is not None:
                hold.release()

    async def _read(
        self, scope: Scope, receive: Receive, send: Send, declared: int | None
    ) -> bytearray | None:
        """The whole body, or None once answered (too slow, too large) or disconnected.

        A ``bytearray``, handed to the app as it is: Starlette's ``Request.body()`` joins what
        it receives into ``bytes`` anyway (a copy even of one message), so a ``bytes`` here
        would be one more copy of every body, on the event loop (~20 ms per 20 MB under load).
        """
        deadline_s = self.limits.deadline_s(declared)
        # One buffer of the declared size, filled in place: no list of chunks beside a joined
        # copy, and one large allocation rather than hundreds of 64 KiB ones.
        buffer = bytearray(declared) if declared is not None else bytearray()
        received = 0
        try:
            async with asyncio.timeout(deadline_s):
                while True:
                    message = await receive()
                    if message["type"] != "http.request":  # client went away
                        return None
                    chunk = message.get("body", b"")
                    end = received + len(chunk)
                    if end > self.limits.max_bytes:
                        raise _TooLarge
                    if declared is not None:
                        buffer[received:end] = chunk
                    else:
                        buffer += chunk
                    received = end
                    if not message.get("more_body", False):
                        break
        except TimeoutError:
            _log.info(
                "%s %s: the body had %d of %s bytes after %.1f s; answering 408",
                scope.get("method"),
                scope.get("path"),
                received,
                declared if declared is not None else "(streamed)",
                deadline_s,
            )
            await send_problem(
                send,
                scope,
                ProblemDetails(
                    type=problem_type("request-body-timeout"),
                    title="Request Timeout",
                    status=408,
                    detail=f"the request body did not arrive within {deadline_s:.3g} s "
                    f"({received} bytes came); send it faster, or a smaller one",
                    instance=scope.get("path"),
                ),
            )
            return None
        except _TooLarge:
            await self._too_large(scope, send, "the streamed request body")
            return None
        del buffer[received:]  # a server holds the client to its Content-Length; be sure
        return buffer

    async def _too_large(self, scope: Scope, send: Send, what: str) -> None:
        error = PayloadTooLargeError(f"{what} exceeds the limit of {self.limits.max_bytes} bytes")
        await send_problem(send, scope, error.problem(instance=scope.get("path")))

    async def _busy(self, scope: Scope, send: Send, budget: BodyBudget, size: int) -> None:
        _log.warning(
            "%s %s: %d body bytes did not fit in %.1f s (%d held, %d waiting); answering 503",
            scope.get("method"),
            scope.get("path"),
            size,
            budget.wait_s,
            budget.in_use,
            budget.waiting,
        )
        error = ServiceUnavailableError(
            f"the service is receiving as many request bodies as it holds at once and {size} "
            f"more bytes did not fit within {budget.wait_s:g} s; try again shortly",
            slug="busy",
            title="Service busy",
        )
        retry_after = str(max(1, math.ceil(budget.wait_s)))
        await send_problem(
            send, scope, error.problem(scope.get("path")), {"Retry-After": retry_after}
        )


def _replay(body: bytearray, receive: Receive) -> Receive:
    """``receive`` that gives the app ``body`` first, in one message, then defers to the server
    (a disconnect)."""
    pending: list[bytearray] = [body]

    async def replayed() -> Message:
        if pending:
            return {"type": "http.request", "body": pending.pop(), "more_body": False}
        return await receive()

    return replayed
