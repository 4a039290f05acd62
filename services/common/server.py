"""The HTTP server every service runs in: uvicorn, with a limit on the size of a request head and
a deadline for receiving it.

Run a service with ``python -m services.common.server services.renderer.app:app --port 8001``
(what ``cosmos up``, the tests and the container image do).

Why: uvicorn bounds neither. Its ``--h11-max-incomplete-event-size`` only reaches the h11 parser,
and with httptools installed (a dependency: the faster parser) uvicorn uses httptools, which
buffers a header of any size: a 64 MB header was answered 200 after 7 s. And no uvicorn timer
runs while a request head is arriving: ``--timeout-keep-alive`` is disarmed by the first byte of
a request (uvicorn issue #157 lists a ``--timeout-request-start`` that was never added), so 2,000
connections that had sent half a head were all still open 30 s later.

What :class:`HttpProtocol` measures, per connection:

* the request head (request line and header fields): the bytes received while it is incomplete,
  and once parsed, the size of its parts. Over ``max_head_bytes`` the client gets 431 (RFC 6585)
  and the connection is closed, before the app runs.
* the time from the connection's opening, or from the first byte of a later request on it, until
  that request's head is complete. Past ``head_timeout_s`` the connection is closed (with a 408
  if part of a head had arrived). A request body and the app's own time are not counted: the
  deadline ends with the head. The body has a deadline of its own, scaled by its size, and is
  bounded by bytes in flight: :mod:`services.common.bodies`.

And when asked to stop, the server sets :data:`~services.common.stopping.STOPPING` (the
endless event streams end themselves), then gives the responses still in flight
``--timeout-graceful-shutdown`` seconds.

Secrets never reach a log line (:class:`RedactSecrets`): a key sent in the query string
(``?api_key=…``, refused by the controller) was written verbatim to the access log. The values of
query parameters with sensitive names (``api_key``, ``token``, ``access_token``, ``password``,
any name ending in ``key``, ``token`` or ``secret`` …), ``Bearer`` credentials and anything shaped
like a COSMOS API key are replaced by ``REDACTED`` in every line of the server's log handlers.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import re
from collections.abc import Sequence
from types import FrameType
from typing import Any, Final

import uvicorn
from uvicorn.config import Config
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.server import ServerState

from services.common.errors import ProblemDetails, StartupError, problem_type
from services.common.stopping import STOPPING

__all__ = [
    "DEFAULT_GRACEFUL_SHUTDOWN_S",
    "DEFAULT_HEAD_TIMEOUT_S",
    "DEFAULT_MAX_HEAD_BYTES",
    "HttpProtocol",
    "RedactSecrets",
    "StartupErrorsInOneLine",
    "guarded_protocol",
    "main",
    "redact",
    "redact_logs",
]

DEFAULT_MAX_HEAD_BYTES: Final = 64 * 1024
"""Request line and headers; a real request of these services sends a few hundred bytes."""
DEFAULT_HEAD_TIMEOUT_S: Final = 10.0
"""A head arrives in one packet on loopback and a LAN; ten seconds is generous for any client."""
DEFAULT_GRACEFUL_SHUTDOWN_S: Final = 8.0
"""What a stopping server gives the responses in flight (a render, a detection) before it
cancels them: the app's own shutdown (a controller's searches checkpointed) still fits in the
10 s Docker waits before it kills a container (15 s for the local launcher)."""

_log = logging.getLogger("cosmos.server")


def _problem(status: int, slug: str, title: str, detail: str) -> bytes:
    """A complete HTTP/1.1 response with a problem+json body that closes the connection."""
    problem = ProblemDetails(type=problem_type(slug), title=title, status=status, detail=detail)
    body = json.dumps(problem.model_dump(mode="json", exclude_none=True)).encode()
    head = (
        f"HTTP/1.1 {status} {title}\r\n"
        "content-type: application/problem+json\r\n"
        f"content-length: {len(body)}\r\n"
        "connection: close\r\n\r\n"
    )
    return head.encode("latin-1") + body


class _HeadTooLarge(Exception):
    """Raised inside the parser's callback to stop parsing a head that is too large."""


class HttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a request head size limit and a head deadline.

    ``max_head_bytes`` is uvicorn's ``h11_max_incomplete_event_size`` when that is set (so one
    setting bounds both parsers), else the class attribute; ``head_timeout_s`` is the class
    attribute (see :func:`guarded_protocol`).
    """

    max_head_bytes: int = DEFAULT_MAX_HEAD_BYTES
    head_timeout_s: float = DEFAULT_HEAD_TIMEOUT_S

    def __init__(
        self,
        config: Config,
        server_state: ServerState,
        app_state: dict[str, Any],
        _loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        super().__init__(config, server_state, app_state, _loop)
        if config.h11_max_incomplete_event_size is not None:
            self.max_head_bytes = config.h11_max_incomplete_event_size
        self._reading_head = True  # until the head of the current request is complete
        self._head_bytes = 0  # bytes received while it was incomplete
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_refused = False

    # -- the deadline ------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_timed_out)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.transport.is_closing() or not self._reading_head:
            return
        if self.cycle is not None and not self.cycle.response_complete:
            # A pipelined head trickles in while the previous request is answered: the answer
            # goes out, then the connection closes.
            self.cycle.keep_alive = False
            return
        if self._head_bytes:
            _log.info(
                "closing %s: request head incomplete after %.0f s (%d bytes)",
                self._peer(),
                self.head_timeout_s,
                self._head_bytes,
            )
            self.transport.write(
                _problem(
                    408,
                    "request-head-timeout",
                    "Request Timeout",
                    f"the request head was not complete within {self.head_timeout_s:g} s",
                )
            )
        self.transport.close()

    # -- the size limit ----------------------------------------------------------------------

    def data_received(self, data: bytes) -> None:
        if self._reading_head:
            self._head_bytes += len(data)
            self._arm_head_timer()
        super().data_received(data)
        if (
            self._reading_head
            and self._head_bytes > self.max_head_bytes
            and not self.transport.is_closing()
        ):
            self._refuse_head(f"{self._head_bytes} bytes and incomplete")

    def on_message_complete(self) -> None:
        self._reading_head = True  # what arrives next is the next request's head
        super().on_message_complete()

    def on_headers_complete(self) -> None:
        self._reading_head = False
        self._head_bytes = 0
        self._cancel_head_timer()
        # A head that arrived whole in one read is measured here, by its parts.
        size = len(self.url) + sum(len(name) + len(value) + 4 for name, value in self.headers)
        if size > self.max_head_bytes:
            self._head_refused = True
            raise _HeadTooLarge  # stops the parser; it reports a parser error, see below
        super().on_headers_complete()

    def send_400_response(self, msg: str) -> None:
        if self._head_refused:
            self._refuse_head("as parsed")
        else:
            super().send_400_response(msg)

    def _refuse_head(self, measured: str) -> None:
        self._cancel_head_timer()
        _log.warning("refusing %s: request head over %d bytes", self._peer(), self.max_head_bytes)
        self.transport.write(
            _problem(
                431,
                "request-head-too-large",
                "Request Header Fields Too Large",
                f"the request line and headers ({measured}) exceed the limit of "
                f"{self.max_head_bytes} bytes",
            )
        )
        self.transport.close()

    def _peer(self) -> str:
        return f"{self.client[0]}:{self.client[1]}" if self.client else "a client"


def guarded_protocol(
    max_head_bytes: int = DEFAULT_MAX_HEAD_BYTES, head_timeout_s: float = DEFAULT_HEAD_TIMEOUT_S
) -> type[HttpProtocol]:
    """:class:`HttpProtocol` with these limits."""
    if max_head_bytes < 1024 or not head_timeout_s > 0.0:
        raise ValueError("max_head_bytes must be at least 1024 and head_timeout_s positive")
    return type(
        "HttpProtocol",
        (HttpProtocol,),
        {"max_head_bytes": max_head_bytes, "head_timeout_s": float(head_timeout_s)},
    )


_SECRET_QUERY = re.compile(
    r"(?i)(?<=[?&;])"
    r"([^=&;#?\s\"']*(?:key|token|secret|passw(?:or)?d|pwd|signature|auth|authorization|"
    r"session|sessionid|jwt|credentials?))"
    r"=[^&;#\s\"']*"
)
"""A query parameter whose name says it holds a secret, and its value."""
_BEARER = re.compile(r"(?i)\b(bearer\s+)[^\s\"',;]+")
_API_KEY = re.compile(r"\bcosmos_[A-Za-z0-9_-]{32,}")
"""A COSMOS API key (``cosmos_`` and 43 characters), wherever it appears."""
REDACTED: Final = "REDACTED"
_FORMATTER = logging.Formatter()


def redact(text: str) -> str:
    """``text`` with the secrets in it replaced by ``REDACTED``: the values of sensitive query
    parameters, ``Bearer`` credentials and API keys."""
    text = _SECRET_QUERY.sub(rf"\1={REDACTED}", text)
    text = _BEARER.sub(rf"\1{REDACTED}", text)
    return _API_KEY.sub(REDACTED, text)


class RedactSecrets(logging.Filter):
    """Redacts (:func:`redact`) every record that passes: the access log's arguments one by one
    (uvicorn's access formatter unpacks them), any other record's whole message and traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == "uvicorn.access" and isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
            return True
        message = record.getMessage()
        redacted = redact(message)
        if redacted != message:
            record.msg, record.args = redacted, None
        if record.exc_info and not record.exc_text:  # a traceback may quote a request too
            record.exc_text = redact(_FORMATTER.formatException(record.exc_info))
        return True


def redact_logs() -> None:
    """Put :class:`RedactSecrets` on every handler of the logging uvicorn configured (its own
    and the access log's), and on the handler of last resort, which writes the records of
    loggers without one (the services' own)."""
    redacting = RedactSecrets()
    loggers = (
        logging.getLogger(),
        logging.getLogger("uvicorn"),
        logging.getLogger("uvicorn.access"),
    )
    handlers = {handler for logger in loggers for handler in logger.handlers}
    if logging.lastResort is not None:
        handlers.add(logging.lastResort)
    for handler in handlers:
        if not any(isinstance(f, RedactSecrets) for f in handler.filters):
            handler.addFilter(redacting)


class StartupErrorsInOneLine(logging.Filter):
    """Drops uvicorn's traceback of a start-up that failed with a
    :class:`~services.common.errors.StartupError`: the app logged its one line already."""

    def filter(self, record: logging.LogRecord) -> bool:
        return f"{StartupError.__module__}.{StartupError.__name__}:" not in record.getMessage()


class _Server(uvicorn.Server):
    """uvicorn's server, which sets :data:`~services.common.stopping.STOPPING` when asked to
    stop."""

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        STOPPING.set()
        super().handle_exit(sig, frame)


def main(argv: Sequence[str] | None = None) -> None:
    """Serve ``APP`` (``module:attribute``) with uvicorn and :class:`HttpProtocol`."""
    parser = argparse.ArgumentParser(
        prog="python -m services.common.server",
        description="Run a COSMOS service: uvicorn with a request head size limit and deadline.",
    )
    parser.add_argument("app", help="the ASGI app, e.g. services.renderer.app:app")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument(
        "--max-head-bytes",
        type=int,
        default=DEFAULT_MAX_HEAD_BYTES,
        help="request line and headers; more gets 431 (default: %(default)s)",
    )
    parser.add_argument(
        "--head-timeout-s",
        type=float,
        default=DEFAULT_HEAD_TIMEOUT_S,
        help="seconds a connection has to send a complete request head (default: %(default)s)",
    )
    parser.add_argument(
        "--timeout-keep-alive",
        type=float,
        default=float(os.environ.get("UVICORN_TIMEOUT_KEEP_ALIVE", "5")),
        help="seconds an idle kept-alive connection stays open; like uvicorn's own command, "
        "UVICORN_TIMEOUT_KEEP_ALIVE sets the default (default: %(default)s)",
    )
    parser.add_argument(
        "--timeout-graceful-shutdown",
        type=float,
        default=DEFAULT_GRACEFUL_SHUTDOWN_S,
        help="seconds a stopping server waits for the responses in flight before it cancels "
        "them (default: %(default)s)",
    )
    args = parser.parse_args(argv)
    try:
        protocol = guarded_protocol(args.max_head_bytes, args.head_timeout_s)
    except ValueError as exc:
        parser.error(str(exc))
    config = Config(
        args.app,
        host=args.host,
        port=args.port,
        http=protocol,
        h11_max_incomplete_event_size=args.max_head_bytes,
        timeout_keep_alive=args.timeout_keep_alive,
        timeout_graceful_shutdown=args.timeout_graceful_shutdown,
    )
    redact_logs()  # after Config, which configures logging
    logging.getLogger("uvicorn.error").addFilter(StartupErrorsInOneLine())
    _Server(config).run()


if __name__ == "__main__":
    main()
