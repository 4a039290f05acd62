"""The base of the services' small synchronous clients: one httpx client, explicit timeouts,
the service token a stage asks for, errors that carry the service's problem detail."""

from __future__ import annotations

from collections.abc import Iterator
from types import TracebackType
from typing import ClassVar, Final, Self

import httpx

from services.common.auth import bearer

__all__ = ["PIECE_BYTES", "ServiceCallError", "ServiceClient", "in_pieces"]

PIECE_BYTES: Final = 1 << 20


def in_pieces(body: bytes, size: int = PIECE_BYTES) -> Iterator[bytes]:
    """``body`` in pieces of ``size`` bytes, for an httpx request's ``content`` (with its
    ``Content-Length`` header set, so it is not sent chunked).

    Why: httpx's synchronous transport sends each part of a body by slicing off what the socket
    took after every ``send`` (``buffer = buffer[n:]``), copying the rest, under the GIL. One
    48 MiB part is copied over and over; the slower the link, the more sends and copies.
    ``python -m benchmarks.upload_pieces`` (50 such uploads at once from one process) measures
    it: whole, 21.1 s of the clients' CPU, and the last request head reached the server 14.6 s
    after the threads were let go (past a service's 10 s head deadline); in 1 MiB pieces,
    1.3 s and 0.17 s (one run, the machine otherwise idle: 15.7× less CPU)."""
    for start in range(0, len(body), size):
        yield body[start : start + size]


class ServiceCallError(RuntimeError):
    """A service answered with an error; the message is its problem detail."""

    def __init__(self, service: str, status: int, detail: str) -> None:
        super().__init__(f"{service} answered {status}: {detail}")
        self.status = status
        self.detail = detail


class ServiceClient:
    """Calls one service at ``base_url`` (sending ``token``, the stack's service token, which
    the stages require); subclasses add the routes."""

    service: ClassVar[str] = "service"
    error: ClassVar[type[ServiceCallError]] = ServiceCallError

    def __init__(self, base_url: str, timeout_s: float = 60.0, *, token: str | None = None) -> None:
        self._http = httpx.Client(
            base_url=base_url, timeout=httpx.Timeout(timeout_s, connect=5.0), headers=bearer(token)
        )

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _check(self, response: httpx.Response) -> httpx.Response:
        """``response``, or the service's error when it answered 4xx/5xx."""
        if response.status_code >= 400:
            response.read()
            try:
                detail = str(response.json().get("detail", response.text))
            except (ValueError, AttributeError):
                detail = response.text
            raise self.error(self.service, response.status_code, detail)
        return response
