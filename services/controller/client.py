"""A small synchronous client of the controller: submit a search, follow it, fetch its plots.

Submitting waits out the controller's refusals that say when to come back (with tenacity): a
429 (a quota of the key) or a 503 (the body budget full, a stage unavailable) with
``Retry-After`` is asked again after ``min(Retry-After, max_wait_s)`` seconds (at least 0.5 s),
while the total wait stays within ``retry_budget_s``; a refusal whose ``Retry-After`` falls
beyond the budget ends the submission at once, with the controller's own problem detail. Any
other error (a 4xx, a 5xx without ``Retry-After``) ends it at once: asking again would get the
same answer.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from typing import Any, Final

import httpx
import tenacity

from services.common.client import ServiceCallError, ServiceClient, in_pieces
from services.common.contracts.search import Iteration, Search
from services.common.images import media_type_of

__all__ = [
    "DEFAULT_MAX_WAIT_S",
    "DEFAULT_RETRY_BUDGET_S",
    "MIN_WAIT_S",
    "RETRYABLE_STATUSES",
    "ControllerClient",
    "ControllerError",
    "retry_after_s",
]

DEFAULT_RETRY_BUDGET_S: Final = 60.0
"""Seconds :meth:`ControllerClient.submit` waits in all for a refusing controller by default."""
DEFAULT_MAX_WAIT_S: Final = 10.0
"""The longest single wait, whatever ``Retry-After`` says: a quota's minute is asked again sooner
(the controller answers the time left), and a wrong or hostile header cannot park the client."""
MIN_WAIT_S: Final = 0.5
"""The shortest wait, whatever ``Retry-After`` says (``0`` would ask again at once, for ever)."""
RETRYABLE_STATUSES: Final = frozenset({429, 503})
"""Refusals that are waited out when they carry ``Retry-After``."""


class ControllerError(ServiceCallError):
    """The controller answered with an error; :attr:`retry_after_s` is its ``Retry-After``."""

    retry_after_s: float | None = None
    """Seconds the answer's ``Retry-After`` asked to wait (None: it had none)."""
    waited_s: float = 0.0
    """Seconds :meth:`ControllerClient.submit` waited out refusals before this one ended it."""


Waiting = Callable[[ControllerError, float], None]
"""Told of each refusal that is waited out: the refusal and the seconds about to be waited."""


def retry_after_s(value: str | None, now: datetime | None = None) -> float | None:
    """Seconds a ``Retry-After`` header asks to wait (RFC 9110 §10.2.3: delay-seconds or an
    HTTP-date); None when absent or unreadable."""
    if value is None:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError):
        return None
    if when.tzinfo is None:  # an HTTP-date is GMT
        when = when.replace(tzinfo=UTC)
    return max(0.0, (when - (now or datetime.now(UTC))).total_seconds())


def _waitable(error: BaseException) -> bool:
    """Whether ``error`` is a refusal that says when to come back."""
    return (
        isinstance(error, ControllerError)
        and error.retry_after_s is not None
        and error.status in RETRYABLE_STATUSES
    )


def _refusal(state: tenacity.RetryCallState) -> ControllerError:
    """The refusal that ended the attempt of ``state`` (only waitable ones are retried)."""
    error = state.outcome.exception() if state.outcome is not None else None
    if not isinstance(error, ControllerError):
        raise TypeError(f"not a refusal of the controller: {error!r}")
    return error


def _after_s(state: tenacity.RetryCallState) -> float:
    """Seconds the last refusal asks to wait, at least :data:`MIN_WAIT_S` (never a busy loop)."""
    return max(_refusal(state).retry_after_s or 0.0, MIN_WAIT_S)


class ControllerClient(ServiceClient):
    """Calls the controller at ``base_url`` with explicit timeouts, sending ``api_key`` as
    ``Authorization: Bearer`` (:func:`services.controller.keys.client_key` finds the local one)."""

    service = "controller"
    error = ControllerError

    def __init__(
        self, base_url: str, timeout_s: float = 60.0, *, api_key: str | None = None
    ) -> None:
        super().__init__(base_url, timeout_s)
        if api_key is not None:
            self._http.headers["Authorization"] = f"Bearer {api_key}"

    def submit(
        self,
        image: bytes,
        scene: str,
        *,
        retry_budget_s: float = DEFAULT_RETRY_BUDGET_S,
        max_wait_s: float = DEFAULT_MAX_WAIT_S,
        on_wait: Waiting | None = None,
        sleep: Callable[[float], object] = time.sleep,
        **options: Any,
    ) -> Search:
        """``POST /searches`` with the image as the body; ``options`` are the optional
        :class:`~services.common.contracts.search.SearchOptions` (None values left out).

        A 429 or 503 with ``Retry-After`` r is asked again after w = min(max(r, 0.5 s),
        ``max_wait_s``) seconds while the waits so far plus max(r, 0.5 s) stay within
        ``retry_budget_s`` (0: never asked again); ``on_wait`` hears of each wait first, and
        ``sleep`` waits (an interruptible one may raise to give up). Then
        :class:`ControllerError` with the last refusal's detail."""
        if retry_budget_s < 0 or not max_wait_s > 0:
            raise ValueError("retry_budget_s must not be negative and max_wait_s positive")
        query = {k: str(v) for k, v in options.items() if v is not None}

        def pause(seconds: float) -> None:
            sleep(seconds)

        def before_sleep(state: tenacity.RetryCallState) -> None:
            if on_wait is not None:
                on_wait(_refusal(state), state.upcoming_sleep)

        retrying = tenacity.Retrying(
            retry=tenacity.retry_if_exception(_waitable),
            wait=lambda state: min(_after_s(state), max_wait_s),
            # Stopped before a wait that would pass the budget: waits so far + the one asked.
            stop=lambda state: state.idle_for + _after_s(state) > retry_budget_s,
            sleep=pause,
            before_sleep=before_sleep,
            reraise=True,  # the controller's own refusal, not tenacity's RetryError
        )
        for attempt in retrying:
            with attempt:
                try:
                    response = self._check(
                        self._http.post(
                            "/searches",
                            content=in_pieces(image),
                            params={"scene": scene, **query},
                            headers={
                                "Content-Type": media_type_of(image),
                                "Content-Length": str(len(image)),
                            },
                        )
                    )
                except ControllerError as refusal:
                    refusal.waited_s = attempt.retry_state.idle_for
                    raise
        return Search.model_validate(response.json())

    def _check(self, response: httpx.Response) -> httpx.Response:
        """``response``, or :class:`ControllerError` with its ``Retry-After``."""
        try:
            return super()._check(response)
        except ControllerError as exc:
            exc.retry_after_s = retry_after_s(response.headers.get("Retry-After"))
            raise

    def get(self, search_id: str) -> Search:
        return Search.model_validate(self._check(self._http.get(f"/searches/{search_id}")).json())

    def follow(self, search_id: str, timeout_s: float = 600.0) -> Iterator[Iteration | Search]:
        """Iterations as they are recorded, then the finished search (server-sent events)."""
        with self._http.stream(
            "GET", f"/searches/{search_id}/events", timeout=httpx.Timeout(timeout_s, connect=5.0)
        ) as response:
            self._check(response)
            event = ""
            for line in response.iter_lines():
                if line.startswith("event: "):
                    event = line[len("event: ") :]
                elif line.startswith("data: "):
                    data = json.loads(line[len("data: ") :])
                    if event == "iteration":
                        yield Iteration.model_validate(data)
                    elif event == "end":
                        yield self.get(search_id)
                        return

    def plot(self, search_id: str, name: str) -> bytes:
        """``trajectory.png`` or ``distance.png``."""
        return self._check(self._http.get(f"/searches/{search_id}/{name}")).content
