"""Where the broker sends a task: the replica choice and what it learns from each outcome.

Pure and clock-free (the caller passes ``now`` and the turn), so the live
:class:`~services.controller.broker.Broker` and the simulation in ``benchmarks.broker_sim`` run
the same code. The heuristics (:func:`choose`):

* ``least-loaded``: fewest tasks ahead, :attr:`Replica.load` (this controller's in flight, plus
  those its last ``/health`` counted beyond this controller's own then);
* ``shortest-expected-completion``: smallest :math:`(L_r + 1)\\,\\hat d_r`, with :math:`L_r` the
  load and :math:`\\hat d_r` the exponential moving average of the replica's recent durations for
  this kind of task, :math:`\\hat d \\leftarrow \\hat d + w (d - \\hat d)`, :math:`w` =
  :data:`EWMA_WEIGHT` (a replica with no history is assumed as fast as the pool's mean);
* ``round-robin``: the next replica in turn.

Ties go to the first in the pool rotated by the turn, so equal replicas take turns.

A task may name a replica it would ``prefer`` (one that holds its data: the optimizer that keeps
a search's target maps, :mod:`services.optimizer.free.target_maps`). It goes there when that
replica has no more tasks ahead of it than the heuristic's choice: the data saves the target's
decoding and maps (measured with ``benchmarks/target_maps.py``: 10 ms on a 320 px film, 64 ms
on a 4000 x 3000 JPEG), while a task ahead costs a whole refinement (30-90 ms), so the
preference never queues a task behind more work.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

from services.common.contracts.search import ReplicaState

__all__ = [
    "DEFAULT_EXPECTED_MS",
    "EWMA_WEIGHT",
    "Heuristic",
    "Replica",
    "candidates",
    "choose",
    "expected_ms",
]

EWMA_WEIGHT = 0.3
DEFAULT_EXPECTED_MS = 100.0


class Heuristic(StrEnum):
    LEAST_LOADED = "least-loaded"
    SHORTEST_EXPECTED = "shortest-expected-completion"
    ROUND_ROBIN = "round-robin"


@dataclass
class Replica:
    """One service replica and what the broker knows of it; ``name`` is what the public sees
    of it, ``url`` is for the log."""

    stage: str
    url: str
    name: str
    in_flight: int = 0
    reported_load: float = 0.0
    """Tasks in flight the replica's last ``/health`` reported (every controller's)."""
    in_flight_at_report: int = 0
    """This controller's tasks in flight when that answer came."""
    expected_ms: dict[str, float] = field(default_factory=dict)
    consecutive_failures: int = 0
    down_until: float = 0.0
    served: int = 0
    failed: int = 0

    @property
    def load(self) -> float:
        """Tasks ahead of a new one: this controller's in flight, plus what the last ``/health``
        counted beyond them (other controllers' tasks, or tasks this one gave up waiting for).

        Not ``max(in_flight, reported)``: a report is up to a probe interval old, and the queue it
        counted (this controller's own tasks, mostly) has often drained since. Simulated
        (``benchmarks.broker_sim``), that stale count kept idle replicas out for up to 2 s after
        a burst and doubled the p99 latency of searches against an oracle's.
        """
        return self.in_flight + max(0.0, self.reported_load - self.in_flight_at_report)

    def available(self, now: float) -> bool:
        return now >= self.down_until

    def state(self, now: float) -> ReplicaState:
        """``out`` while taken out after failures, ``failing`` while its last task or probe
        failed (it still gets tasks), else ``up``."""
        if not self.available(now):
            return "out"
        return "failing" if self.consecutive_failures else "up"

    def succeeded(self, kind: str, elapsed_ms: float) -> None:
        """A ``kind`` task took ``elapsed_ms``: fold it into the moving average, clear failures."""
        previous = self.expected_ms.get(kind)
        self.expected_ms[kind] = (
            elapsed_ms if previous is None else previous + EWMA_WEIGHT * (elapsed_ms - previous)
        )
        self.consecutive_failures = 0
        self.down_until = 0.0
        self.served += 1

    def failed_at(self, now: float, threshold: int, cooldown_s: float) -> bool:
        """A task or probe failed at ``now``; True when this takes the replica out until
        ``now + cooldown_s`` (its ``threshold``-th failure in a row)."""
        self.failed += 1
        self.consecutive_failures += 1
        if self.consecutive_failures >= threshold:
            self.down_until = now + cooldown_s
            return True
        return False

    def answered_health(self, reported_load: float) -> None:
        """``/health`` answered with this load: the replica is back in."""
        self.reported_load = reported_load
        self.in_flight_at_report = self.in_flight
        self.down_until = 0.0
        self.consecutive_failures = 0


def _pool_mean_ms(pool: Sequence[Replica], kind: str) -> float:
    """The mean of the pool's moving averages for ``kind``, else :data:`DEFAULT_EXPECTED_MS`."""
    known = [r.expected_ms[kind] for r in pool if kind in r.expected_ms]
    return sum(known) / len(known) if known else DEFAULT_EXPECTED_MS


def expected_ms(replica: Replica, kind: str, pool: Sequence[Replica]) -> float:
    """The replica's expected duration of a ``kind`` task: its moving average, else the pool's
    mean, else :data:`DEFAULT_EXPECTED_MS`."""
    if kind in replica.expected_ms:
        return replica.expected_ms[kind]
    return _pool_mean_ms(pool, kind)


def candidates(pool: Sequence[Replica], now: float, exclude: Collection[str]) -> list[Replica]:
    """The replicas a task may go to: those in, not in ``exclude`` (urls); if none, those not
    excluded; if none, the whole pool."""
    available = [r for r in pool if r.available(now) and r.url not in exclude]
    return available or [r for r in pool if r.url not in exclude] or list(pool)


def choose(
    heuristic: Heuristic,
    pool: Sequence[Replica],
    kind: str,
    *,
    turn: int,
    now: float,
    exclude: Collection[str] = (),
    prefer: str | None = None,
) -> Replica:
    """The replica of a non-empty ``pool`` for the next ``kind`` task, by ``heuristic``, at
    ``now`` and the stage's ``turn`` (a counter the caller advances once per choice); the one
    at the url ``prefer`` instead when it may take the task and has no more ahead of it
    (module docstring)."""
    if not pool:
        raise ValueError("an empty pool has no replica to choose")
    among = candidates(pool, now, exclude)
    chosen = _by_heuristic(heuristic, pool, among, kind, turn)
    held = next((r for r in among if r.url == prefer), None)
    return held if held is not None and held.load <= chosen.load else chosen


def _by_heuristic(
    heuristic: Heuristic, pool: Sequence[Replica], among: list[Replica], kind: str, turn: int
) -> Replica:
    """The heuristic's choice among the ``among`` replicas of ``pool`` (module docstring)."""
    start = turn % len(among)
    if heuristic is Heuristic.ROUND_ROBIN:
        return among[start]
    rotated = among[start:] + among[:start]
    if heuristic is Heuristic.LEAST_LOADED:
        return min(rotated, key=lambda r: r.load)
    fallback = _pool_mean_ms(pool, kind)  # once, not once per replica without history
    return min(rotated, key=lambda r: (r.load + 1.0) * r.expected_ms.get(kind, fallback))
