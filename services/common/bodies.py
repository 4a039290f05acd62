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
  body never kept (see *early answers* below). A chunked body, of unknown length, holds
  ``max_bytes`` while it streams and gives back what it did not use once it has arrived.
* **time**: the body must have arrived within ``timeout_s + size / min_bytes_per_s`` of its
  admission (``size`` the declared length, or ``max_bytes`` when chunked), else 408 and the
  connection is closed; its bytes are given back at once. A trickling client holds a budget's
  share no longer than that.

**Early answers** (413 by ``Content-Length``, 503, 408, and the 401s of the stages' service
token and the controller's API keys, before a body is read) close the connection, but not at
once: what still arrives of the body is read and dropped (:func:`send_problem` with
``receive``) until it ends, for at most :data:`LINGER_S`, and :data:`LINGER_IDLE_S` without a
byte. Why (RFC 9112 §9.6): a server that closes a connection with unread bytes in it sends a
TCP reset, not a FIN, and a client still writing its body (most send all of it before they
read) may have the answer thrown away with the reset on its way: some TCP stacks discard what
they received but the application had not yet read. Measured over raw sockets
(``tests/common/test_bodies.py``, ``tests/detector/test_http.py``), a refused upload sent whole
ended in a reset before, and ends in a FIN now. The dropped bytes are never held, nor counted
in the budget: what this costs is the reading, 1.6 s of the server's CPU per GB dropped (20
refused 48 MiB uploads over loopback, one run), so at most :data:`LINGER_S` of a connection's
bandwidth.

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
    "LINGER_IDLE_S",
    "LINGER_S",
    "BodyBudget",
    "BodyLimits",
    "BodyMiddleware",
    "Hold",
    "declared_length",
    "drop_rest",
    "has_body",
    "send_problem",
]

DEFAULT_BODY_TIMEOUT_S: Final = 10.0
"""Seconds any body has to arrive, on top of its size's share (a LAN sends 20 MB in 0.2 s)."""
DEFAULT_MIN_BYTES_PER_S: Final = 512 * 1024
"""The slowest upload served in full: 4 Mbit/s, so a 20 MiB body may take 40 s more."""
LINGER_S: Final = 10.0
"""Seconds an early answer's connection goes on reading (and dropping) the request's body."""
LINGER_IDLE_S: Final = 2.0
"""…and seconds it waits for the next byte of it, as nginx's ``lingering_timeout`` (5 s)."""
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
    send: Send,
    scope: Scope,
    problem: ProblemDetails,
    headers: dict[str, str] | None = None,
    *,
    receive: Receive | None = None,
) -> None:
    """Send ``problem`` as problem+json and have the server close the connection after it (the
    body was not read, or not all of it). With ``receive``, the rest of the body is read and
    dropped first (:func:`drop_rest`), the answer already sent."""
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
    if receive is None:
        await send({"type": "http.response.body", "body": body})
        return
    # The whole answer is on its way; the response ends (and the server closes) after the drop.
    await send({"type": "http.response.body", "body": body, "more_body": True})
    try:
        await drop_rest(receive)
    finally:
        await send({"type": "http.response.body", "body": b""})


async def drop_rest(
    receive: Receive, linger_s: float = LINGER_S, idle_s: float = LINGER_IDLE_S
) -> int:
    """Read what is left of a request's body and drop it, until its end or the client's going
    away, at most ``linger_s`` in all and ``idle_s`` between two messages; the bytes dropped."""
    dropped = 0
    try:
        async with asyncio.timeout(linger_s):
            while True:
                async with asyncio.timeout(idle_s):
                    message = await receive()
                if message["type"] != "http.request":
                    break
                dropped += len(message.get("body", b""))
                if not message.get("more_body", False):
                    break
    except TimeoutError:
        pass
    return dropped


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
            problem = self._too_large(scope, f"the request body of {declared} bytes")
            await send_problem(send, scope, problem, receive=receive)
            return
        hold: Hold | None = None
        if self.budget is not None:
            size = self.limits.max_bytes if declared is None else declared
            hold = await self.budget.acquire(size)
            if hold is None:
                problem, headers = self._busy(scope, self.budget, size)
                await send_problem(send, scope, problem, headers, receive=receive)
                return
        try:
            read = await self._read(scope, receive, declared)
            if isinstance(read, bytearray):
                if hold is not None:
                    hold.shrink(len(read))
                replay = _replay(read, receive)
                del read  # the app holds it from here; it is not kept alive here after the app
                await self.app(scope, replay, send)
                return
        finally:
            if hold is not None:
                hold.release()
        if read is not None:  # too slow or too large; its bytes are free before the rest goes
            await send_problem(send, scope, read, receive=receive)

    async def _read(
        self, scope: Scope, receive: Receive, declared: int | None
    ) -> bytearray | ProblemDetails | None:
        """The whole body; or the problem to answer when it came too slowly or was too large;
        or None when the client went away.

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
            return ProblemDetails(
                type=problem_type("request-body-timeout"),
                title="Request Timeout",
                status=408,
                detail=f"the request body did not arrive within {deadline_s:.3g} s "
                f"({received} bytes came); send it faster, or a smaller one",
                instance=scope.get("path"),
            )
        except _TooLarge:
            return self._too_large(scope, "the streamed request body")
        del buffer[received:]  # a server holds the client to its Content-Length; be sure
        return buffer

    def _too_large(self, scope: Scope, what: str) -> ProblemDetails:
        error = PayloadTooLargeError(f"{what} exceeds the limit of {self.limits.max_bytes} bytes")
        return error.problem(instance=scope.get("path"))

    def _busy(
        self, scope: Scope, budget: BodyBudget, size: int
    ) -> tuple[ProblemDetails, dict[str, str]]:
        """The 503 (and its ``Retry-After``) for ``size`` bytes that did not fit in time."""
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
        return error.problem(scope.get("path")), {"Retry-After": retry_after}


def _replay(body: bytearray, receive: Receive) -> Receive:
    """``receive`` that gives the app ``body`` first, in one message, then defers to the server
    (a disconnect)."""
    pending: list[bytearray] = [body]

    async def replayed() -> Message:
        if pending:
            return {"type": "http.request", "body": pending.pop(), "more_body": False}
        return await receive()

    return replayed
