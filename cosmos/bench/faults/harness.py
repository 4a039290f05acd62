"""The fault suite's measuring tools: a background load of normal searches, a per-service peak
memory sampler, and the arithmetic of what happened to the searches (counts, p95).

What counts (one :class:`Outcome` per normal search the load asked for):

* **submitted**: the controller took the search (202), or refused it for good (any answer but
  202, 429 and 503). A 429 or 503 refusal (quota, a stage unavailable: the controller says "not
  now" with ``Retry-After``) is not a submission: the client asks again, and a search still being
  refused when the load stops is counted as ``refused`` only. A request that got no answer at all
  (the controller died under it) is asked again too, and counted as ``unanswered``.
* **succeeded**: submitted and seen by its client to end ``succeeded``.
* **lost** = submitted − succeeded: a search the controller took that never reached a terminal
  state before the load's drain deadline (``unfinished``), or ended ``failed`` or ``cancelled``
  (``failed``), or vanished (its ``GET`` answered 404), or a submission refused for good. Every
  scenario's normal searches are valid targets that a healthy stack finds, so any of these is the
  fault's doing: the stack should have ridden it out.
* **latency**: from the search's first submission attempt to the moment its client saw it end,
  so it includes refusals while a stage was away and waits while the controller was down. Its
  p95 (:func:`p95`, nearest rank) is taken over the succeeded searches whose life overlaps the
  fault's window (:func:`latencies`).
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import httpx

from cosmos.bench.memory import memory_of, reset_peak
from cosmos.bench.target import Target
from services.common.contracts.search import TERMINAL_STATUSES, Search
from services.controller.client import ControllerClient, ControllerError

__all__ = [
    "MIB",
    "Counts",
    "Load",
    "Outcome",
    "RssSampler",
    "count",
    "latencies",
    "p95",
    "percentile",
]

MIB = 1 << 20


class _Halted(Exception):
    """The load stopped while a submission waited to be asked again."""


def percentile(values: Iterable[float], q: float) -> float | None:
    """The nearest-rank ``q``-th percentile: the smallest value with at least ``q`` % of the
    values at or below it, ``x_(⌈q n / 100⌉)`` of the sorted ``x_(1) ≤ … ≤ x_(n)``; None for no
    values. Always one of the values (no interpolation), so a p95 of 20 searches is the 19th."""
    if not 0.0 < q <= 100.0:
        raise ValueError(f"q must be in (0, 100], not {q}")
    ordered = sorted(values)
    if not ordered:
        return None
    rank = math.ceil(q * len(ordered) / 100.0 - 1e-9)  # 1e-9: 95 * 20 / 100 is 19, not 19.0…01
    return ordered[max(rank, 1) - 1]


def p95(values: Iterable[float]) -> float | None:
    """The nearest-rank 95th percentile (:func:`percentile`)."""
    return percentile(values, 95.0)


@dataclass(frozen=True)
class Outcome:
    """One normal search as its client saw it; times are :func:`time.monotonic` seconds."""

    started_at: float
    """The first submission attempt."""
    search_id: str | None = None
    """The controller's id; None when it never took the search."""
    ended_at: float | None = None
    """When the client saw it end (or was refused for good); None if it never did."""
    status: str | None = None
    """The last status seen, or ``rejected`` for a submission refused for good."""
    error: str | None = None
    """The search's error type, or what went wrong for the client."""
    correct: bool | None = None
    """Whether a succeeded search found the target's grid pose."""
    refusals: int = 0
    """429/503 answers before the controller took it."""
    unanswered: int = 0
    """Submissions that got no answer (connection lost) before it was taken."""

    @property
    def submitted(self) -> bool:
        return self.search_id is not None or self.status == "rejected"

    @property
    def succeeded(self) -> bool:
        return self.status == "succeeded"

    @property
    def lost(self) -> bool:
        return self.submitted and not self.succeeded

    @property
    def latency_s(self) -> float | None:
        return None if self.ended_at is None else self.ended_at - self.started_at

    def overlaps(self, start: float, end: float) -> bool:
        """Whether the search's life (first attempt to end, open if it never ended) meets the
        window [``start``, ``end``]."""
        finish = math.inf if self.ended_at is None else self.ended_at
        return self.started_at <= end and finish >= start


@dataclass(frozen=True)
class Counts:
    """What happened to a set of normal searches (the module's docstring says what counts)."""

    submitted: int
    succeeded: int
    lost: int
    unfinished: int
    """Lost: never seen in a terminal state."""
    failed: int
    """Lost: ended failed or cancelled, vanished, or refused for good."""
    refused: int
    """Still refused (429/503) when the load stopped: never submitted."""
    refusals: int
    """429/503 answers in all."""
    unanswered: int
    """Submissions that got no answer in all (each asked again)."""
    wrong_pose: int
    """Succeeded with another grid pose than the target's (not lost: a search answers)."""


def count(outcomes: Iterable[Outcome]) -> Counts:
    """Tally ``outcomes``."""
    items = list(outcomes)
    submitted = [o for o in items if o.submitted]
    lost = [o for o in submitted if o.lost]
    unfinished = [o for o in lost if o.status not in TERMINAL_STATUSES | {"rejected", "vanished"}]
    return Counts(
        submitted=len(submitted),
        succeeded=sum(o.succeeded for o in submitted),
        lost=len(lost),
        unfinished=len(unfinished),
        failed=len(lost) - len(unfinished),
        refused=sum(not o.submitted and o.refusals > 0 for o in items),
        refusals=sum(o.refusals for o in items),
        unanswered=sum(o.unanswered for o in items),
        wrong_pose=sum(o.succeeded and o.correct is False for o in items),
    )


def latencies(
    outcomes: Iterable[Outcome], window: tuple[float, float] | None = None
) -> list[float]:
    """Latencies (s) of the succeeded searches, only those overlapping ``window`` if given."""
    return [
        o.latency_s
        for o in outcomes
        if o.succeeded and o.latency_s is not None and (window is None or o.overlaps(*window))
    ]


class Load:
    """A closed-loop background load of normal searches through :class:`ControllerClient`.

    ``concurrency`` clients (threads), each with the API key ``api_key``, submit a search of the
    next target (a new seed each time, so starts differ; ``options`` for the rest), poll
    ``GET /searches/{id}`` every ``poll_s`` until it ends, pause ``think_s`` and go on, until
    :meth:`stop`. A 429/503 answer (with ``Retry-After``) is asked again after its
    ``Retry-After``, at most ``refused_wait_s`` (the client's own retrying), a request without an
    answer (controller down) after ``poll_s``; polls that get no answer go on polling. After
    :meth:`stop`, a search in flight is followed until ``drain_s`` has passed, then given up as
    unfinished.
    """

    def __init__(
        self,
        url: str,
        api_key: str,
        targets: Sequence[Target],
        *,
        concurrency: int = 2,
        think_s: float = 0.1,
        poll_s: float = 0.1,
        refused_wait_s: float = 1.0,
        search_timeout_s: float = 300.0,
        first_seed: int = 0,
        options: Mapping[str, Any] | None = None,
    ) -> None:
        if not targets:
            raise ValueError("the load needs at least one target")
        if concurrency < 1:
            raise ValueError("the load needs at least one client")
        self._url = url
        self._key = api_key
        self._targets = list(targets)
        self._concurrency = concurrency
        self._think_s = think_s
        self._poll_s = poll_s
        self._refused_wait_s = refused_wait_s
        self._search_timeout_s = search_timeout_s
        self._options = dict(options or {})
        self._next = itertools.count(first_seed)
        self._lock = threading.Lock()
        self._outcomes: list[Outcome] = []
        self._following: dict[int, str] = {}  # client thread -> the search it follows
        self._stopping = threading.Event()
        self._deadline: float | None = None
        self._threads: list[threading.Thread] = []

    def start(self) -> Load:
        for i in range(self._concurrency):
            thread = threading.Thread(target=self._client, name=f"fault-load-{i}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def halt(self, drain_s: float = 60.0) -> None:
        """Submit nothing more; follow the searches in flight for up to ``drain_s`` more."""
        if not self._stopping.is_set():
            self._deadline = time.monotonic() + drain_s
            self._stopping.set()

    def stop(self, drain_s: float = 60.0) -> list[Outcome]:
        """:meth:`halt`, then wait for the clients to finish; every outcome."""
        self.halt(drain_s)
        deadline = self._deadline or time.monotonic()
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()) + 30.0)
        return self.outcomes

    @property
    def outcomes(self) -> list[Outcome]:
        """The outcomes recorded so far (a search in flight is recorded when it ends)."""
        with self._lock:
            return list(self._outcomes)

    @property
    def in_flight(self) -> list[str]:
        """The ids of the searches being followed now."""
        with self._lock:
            return list(self._following.values())

    def _client(self) -> None:
        with ControllerClient(self._url, timeout_s=60.0, api_key=self._key) as client:
            while not self._stopping.is_set():
                seed = next(self._next)
                target = self._targets[seed % len(self._targets)]
                outcome = self._search(client, target, seed)
                if outcome is not None:
                    with self._lock:
                        self._outcomes.append(outcome)
                self._stopping.wait(self._think_s)

    def _overdue(self, started_at: float) -> bool:
        now = time.monotonic()
        deadline = self._deadline
        return now - started_at > self._search_timeout_s or (
            deadline is not None and now > deadline
        )

    def _pause(self, seconds: float) -> None:
        """Wait ``seconds`` between submission attempts; :class:`_Halted` once the load stops."""
        if self._stopping.wait(seconds):
            raise _Halted

    def _search(self, client: ControllerClient, target: Target, seed: int) -> Outcome | None:
        started = time.monotonic()
        refusals = unanswered = 0

        def refused(refusal: ControllerError, wait_s: float) -> None:
            nonlocal refusals
            refusals += 1

        while True:
            if self._stopping.is_set():  # never taken: nothing to follow
                if refusals == 0 and unanswered == 0:
                    return None
                return Outcome(started, refusals=refusals, unanswered=unanswered)
            try:
                # The client waits out "not now" (429/503 with Retry-After) itself, asking again
                # every min(Retry-After, refused_wait_s) until the load stops.
                search = client.submit(
                    target.image,
                    target.scene,
                    retry_budget_s=math.inf,
                    max_wait_s=self._refused_wait_s,
                    on_wait=refused,
                    sleep=self._pause,
                    seed=seed,
                    **self._options,
                )
            except _Halted:
                continue  # the stopping branch above records it
            except ControllerError as exc:
                return Outcome(
                    started,
                    ended_at=time.monotonic(),
                    status="rejected",
                    error=f"{exc.status}: {exc.detail}",
                    refusals=refusals,
                    unanswered=unanswered,
                )
            except httpx.TransportError:
                unanswered += 1
                self._stopping.wait(self._poll_s)
                continue
            break
        with self._lock:
            self._following[threading.get_ident()] = search.id
        try:
            return self._follow(client, target, search, started, refusals, unanswered)
        finally:
            with self._lock:
                self._following.pop(threading.get_ident(), None)

    def _follow(
        self,
        client: ControllerClient,
        target: Target,
        search: Search,
        started: float,
        refusals: int,
        unanswered: int,
    ) -> Outcome:
        search_id, status, error, result = search.id, search.status, None, search.result
        while status not in TERMINAL_STATUSES:
            if self._overdue(started):
                return Outcome(
                    started, search_id, status=status, refusals=refusals, unanswered=unanswered
                )
            time.sleep(self._poll_s)
            try:
                seen = client.get(search_id)
            except httpx.TransportError:
                continue
            except ControllerError as exc:
                if exc.status == 404:
                    return Outcome(
                        started,
                        search_id,
                        ended_at=time.monotonic(),
                        status="vanished",
                        error=exc.detail,
                        refusals=refusals,
                        unanswered=unanswered,
                    )
                continue  # a 5xx: the controller restarting; the search may still end
            status = seen.status
            error = None if seen.error is None else seen.error.type
            result = seen.result
        correct = None
        if status == "succeeded" and result is not None:
            correct = result.pose.index == target.truth
        return Outcome(
            started,
            search_id,
            ended_at=time.monotonic(),
            status=status,
            error=error,
            correct=correct,
            refusals=refusals,
            unanswered=unanswered,
        )


class RssSampler:
    """Peak resident memory per service over a window, from ``/proc``.

    ``processes`` says which processes run now, as (service name, pid) pairs; it is asked at
    every sample, so replicas started again are followed. :meth:`start` starts the high-water
    mark of each running process over (so a peak before the window is not counted); then every
    ``interval_s`` each process's ``VmHWM`` is read, which the kernel keeps between samples, so
    no spike is missed while the process lives. Where the mark cannot be reset, sampled
    ``VmRSS`` is used instead. A service's peak is the most over its replicas and restarts.
    """

    def __init__(
        self, processes: Callable[[], Iterable[tuple[str, int]]], interval_s: float = 0.2
    ) -> None:
        self._processes = processes
        self._interval_s = interval_s
        self._peaks: dict[str, int] = {}
        self._trust_hwm: dict[int, bool] = {}
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def start(self) -> RssSampler:
        for _, pid in self._processes():
            self._trust_hwm[pid] = reset_peak(pid)
        self.sample()
        self._thread = threading.Thread(target=self._run, name="fault-rss", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stopped.wait(self._interval_s):
            self.sample()

    def sample(self) -> None:
        """Read every process's memory once."""
        for name, pid in self._processes():
            memory = memory_of(pid)
            if memory is None:
                continue
            rss, hwm = memory
            # A process first seen now started within the window: its whole life counts.
            seen = rss if not self._trust_hwm.setdefault(pid, True) else max(rss, hwm)
            with self._lock:
                self._peaks[name] = max(self._peaks.get(name, 0), seen)

    def stop(self) -> dict[str, float]:
        """Stop sampling (after a last sample); the peaks in MiB."""
        self._stopped.set()
        if self._thread is not None:
            self._thread.join()
        self.sample()
        return self.peaks_mib

    @property
    def peaks_mib(self) -> dict[str, float]:
        with self._lock:
            return {name: peak / MIB for name, peak in self._peaks.items()}
