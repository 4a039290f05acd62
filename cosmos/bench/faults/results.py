"""What a fault scenario measures (:class:`Measured`: counts, peak memory, p95 latency, the
fault's window) and each scenario's own facts, one result type per scenario."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from cosmos.bench.faults.harness import (
    Counts,
)

__all__ = [
    "ControllerKilled",
    "DetectorOutage",
    "MaximalUploads",
    "Measured",
    "ReplicaKilled",
    "ScenarioFailure",
    "ScenarioResult",
    "SlowClients",
    "Tenants",
]


@dataclass(frozen=True)
class Measured:
    """What every scenario measures."""

    name: str
    counts: Counts
    peak_rss_mib: Mapping[str, float]
    """Peak resident memory per service (the most over its replicas and restarts) in the run."""
    p95_s: float | None
    """p95 latency of the normal searches overlapping the fault's window."""
    baseline_p95_s: float | None
    """p95 latency of the normal searches that ended before the fault."""
    fault_s: float
    """The fault's window, injection to recovery."""
    errors: tuple[str, ...] = ()
    """The distinct errors of the lost searches."""

    def notes(self) -> str:
        """What the counts say beyond submitted, succeeded and lost."""
        c = self.counts
        parts = []
        if c.refusals:
            parts.append(f"{c.refusals} refusals (429/503) retried, {c.refused} never taken")
        if c.unanswered:
            parts.append(f"{c.unanswered} submissions unanswered, sent again")
        if c.wrong_pose:
            parts.append(f"{c.wrong_pose} found another pose")
        if c.lost:
            parts.append(f"LOST {c.unfinished} unfinished, {c.failed} failed: {list(self.errors)}")
        return "; ".join(parts)


@dataclass(frozen=True)
class ScenarioResult:
    """A scenario's measurements; each scenario's subclass adds its own facts."""

    measured: Measured

    @property
    def name(self) -> str:
        return self.measured.name

    def facts(self) -> str:
        return ""

    def notes(self) -> str:
        return "; ".join(part for part in (self.facts(), self.measured.notes()) if part)


@dataclass(frozen=True)
class ScenarioFailure:
    """A scenario that could not run to its end."""

    name: str
    error: str


@dataclass(frozen=True)
class ReplicaKilled(ScenarioResult):
    supervised: bool
    killed: str
    came_back: bool
    """The killed replica answers again and the controller's broker counts it up."""
    back_after_s: float
    restarts: int
    """Restarts by the supervisor (plain: by the scenario)."""
    served_after: int
    """Tasks the replica served after it came back, to the end of the load."""

    def facts(self) -> str:
        how = f"supervisor restarts {self.restarts}" if self.supervised else "started by hand"
        back = f"back in {self.back_after_s:.1f} s" if self.came_back else "NOT back"
        return f"a {self.killed} of 2 SIGKILLed, {back} ({how}), served {self.served_after} after"


@dataclass(frozen=True)
class DetectorOutage(ScenarioResult):
    outage_s: float
    degraded_seen: bool
    """``/health`` said degraded, naming the detector, during the outage."""
    recovered_after_s: float
    """From the detector's restart (its process started) to the controller's ``/health`` ok:
    the detector's start-up and the broker noticing it."""
    in_flight: int
    """Searches in flight when the detector went down."""
    ridden_out: int
    """Of those, the ones that ended succeeded after it was back."""

    def facts(self) -> str:
        degraded = "yes" if self.degraded_seen else "NO"
        return (
            f"detector down {self.outage_s:.0f} s, /health degraded: {degraded}, ok "
            f"{self.recovered_after_s:.1f} s after its restart; {self.ridden_out} of "
            f"{self.in_flight} searches in flight waited and succeeded"
        )


@dataclass(frozen=True)
class ControllerKilled(ScenarioResult):
    down_s: float
    """SIGKILL to healthy again."""
    in_flight: int
    """Searches in flight when it was killed."""
    resumed: int
    """Of those, the ones that ended succeeded after the restart."""
    orphans: int
    """Searches of the scenario's key that no client got an id for (a submission the controller
    took as it died); they run like any other."""
    orphans_unfinished: int

    def facts(self) -> str:
        orphans = (
            f", {self.orphans} orphans ({self.orphans_unfinished} unfinished)"
            if self.orphans
            else ""
        )
        return (
            f"down {self.down_s:.1f} s; {self.resumed} of {self.in_flight} searches in flight "
            f"resumed and succeeded{orphans}"
        )


@dataclass(frozen=True)
class SlowClients(ScenarioResult):
    sockets: int
    closed_by_server: int
    """Half-sent requests the server closed by the end of the hold."""
    health_checks: int
    health_failures: int
    """``GET /health`` not answered 200 within 5 s while the sockets were open."""
    health_p95_s: float | None

    def facts(self) -> str:
        p95_text = "-" if self.health_p95_s is None else f"{self.health_p95_s * 1000:.0f} ms"
        ok = self.health_checks - self.health_failures
        return (
            f"{self.sockets} half-sent requests, {self.closed_by_server} closed by the server; "
            f"/health {ok}/{self.health_checks} answered, p95 {p95_text}"
        )


@dataclass(frozen=True)
class MaximalUploads(ScenarioResult):
    uploads: int
    body_bytes: int
    limit_bytes: int
    statuses: Mapping[int, int] = field(default_factory=dict)
    """Answers by status."""
    unanswered: int = 0
    """No answer within the timeout (a hang), or the connection dropped."""
    transport_errors: Mapping[str, int] = field(default_factory=dict)
    """The unanswered by what the client saw: the exception's class and its message."""
    badly_answered: int = 0
    """A 5xx other than 503, a 4xx or 503 without problem details, or a 429 or 503 without
    ``Retry-After``."""
    slowest_answer_s: float = 0.0

    def facts(self) -> str:
        answers = ", ".join(f"{n}×{status}" for status, n in sorted(self.statuses.items()))
        return (
            f"{self.uploads} uploads of {self.body_bytes / 2**20:.2f} MiB "
            f"({self.limit_bytes - self.body_bytes} B under the limit): {answers or 'none'}; "
            f"{self.unanswered} unanswered{_kinds(self.transport_errors)}, "
            f"{self.badly_answered} badly answered, slowest {self.slowest_answer_s:.1f} s"
        )


def _kinds(errors: Mapping[str, int]) -> str:
    """`` (2×ReadError: …)``, or nothing when there were none."""
    if not errors:
        return ""
    return " (" + "; ".join(f"{n}×{kind}" for kind, n in sorted(errors.items())) + ")"


@dataclass(frozen=True)
class Tenants(ScenarioResult):
    a_searches: int
    b_searches: int
    checks: int
    """Requests of one tenant for the other's searches (read, cancel, list)."""
    b_saw_a: int
    """Tenant A's searches tenant B could read, cancel or list (must be 0)."""
    a_saw_b: int
    b_lists_own: bool
    """B's list holds every one of B's searches."""

    def facts(self) -> str:
        return (
            f"A {self.a_searches} and B {self.b_searches} searches, {self.checks} cross "
            f"requests: B saw {self.b_saw_a} of A's, A saw {self.a_saw_b} of B's"
        )
