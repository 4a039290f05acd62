"""The fault scenarios of issue 15, each through the real processes of a :class:`~.rig.Rig`.

Every scenario runs a background load of normal searches (:class:`~.harness.Load`:
``Timing.concurrency`` clients with a tenant API key of the scenario's own) and samples every
process's memory (:class:`~.harness.RssSampler`) while it injects its fault: ``warm_s`` of load
first, then the fault, then ``after_s`` of load once the stack has recovered; then the load
stops and the searches in flight are followed to their end (``drain_s`` at most). The fault's
window runs from its injection to the stack's recovery (the replica back in the broker, the
controller healthy again, the slow sockets closed, every upload answered); the p95 latency is
that of the normal searches whose life overlaps it. :mod:`.harness` says what counts as
submitted, succeeded and lost.

Where a fact needs a search in flight across the fault (an outage ridden out, a restarted
controller resuming), a sentinel client runs longer searches beside the load (the ``simple``
strategy from near the pole to :data:`~.rig.FAR`: 12 iterations, ~3 s on an idle machine), and
the fault waits until one of them has recorded two iterations; sentinels count among the normal
searches.

Each scenario is a function of a rig and a :class:`Timing` returning its own result type;
:data:`SCENARIOS` lists them by name, and :func:`run_scenarios` runs a selection on one rig.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

import cv2
import httpx
import numpy as np

from cosmos.bench.faults.harness import (
    Counts,
    Load,
    Outcome,
    RssSampler,
    count,
    latencies,
    p95,
)
from cosmos.bench.faults.rig import Rig, fault_rig, wait_until
from cosmos.bench.target import Target
from services.common.contracts.search import TERMINAL_STATUSES
from services.common.http import PROBLEM_JSON
from services.common.images import PPM_MEDIA_TYPE, decode_image, encode_ppm
from services.controller.client import ControllerClient
from services.controller.settings import ControllerSettings

__all__ = [
    "SCENARIOS",
    "ControllerKilled",
    "DetectorOutage",
    "MaximalUploads",
    "Measured",
    "ReplicaKilled",
    "ScenarioFailure",
    "ScenarioResult",
    "SlowClients",
    "Tenants",
    "Timing",
    "controller_killed",
    "detector_outage",
    "maximal_upload_body",
    "maximal_uploads",
    "replica_killed",
    "replica_killed_supervised",
    "run_scenarios",
    "slow_clients",
    "tenants",
    "well_answered",
]

SENTINEL_OPTIONS: Final[Mapping[str, Any]] = {
    "strategy": "simple",
    "start_theta_deg": 7.5,
    "start_phi_deg": 0.0,
    "max_iterations": 80,
}
MAX_SLOW_SOCKETS: Final = 1000
HALF_HEAD: Final = (
    b"POST /searches HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\nX-Slow: "
)


@dataclass(frozen=True)
class Timing:
    """How long and how hard each scenario pushes; :meth:`quick` for tests and ``--quick``."""

    concurrency: int = 3
    """Clients of the normal load."""
    warm_s: float = 5.0
    """Load before the fault."""
    after_s: float = 5.0
    """Load after the stack recovered."""
    drain_s: float = 90.0
    """How long the searches in flight are followed once the load stops."""
    recover_s: float = 120.0
    """How long a process may take to come back before the scenario says it did not."""
    degraded_s: float = 5.0
    """Plain replica kill: how long the stage runs on its other replica before the killed one
    is started again."""
    outage_s: float = 20.0
    """How long the only detector stays down."""
    controller_down_s: float = 3.0
    """How long the controller stays down after its SIGKILL."""
    slow_sockets: int = 300
    """Half-sent requests held open at once (at most :data:`MAX_SLOW_SOCKETS`)."""
    slow_hold_s: float = 12.0
    """How long they are held once all are open: past the server's 10 s head deadline."""
    uploads: int = 50
    """Maximal uploads at once."""
    upload_timeout_s: float = 120.0
    """An upload unanswered this long has hung."""

    @classmethod
    def quick(cls) -> Timing:
        """Shorter loads and faults (the detector down 5 s instead of 20 s)."""
        return cls(
            concurrency=2,
            warm_s=1.5,
            after_s=1.5,
            drain_s=60.0,
            degraded_s=2.0,
            outage_s=5.0,
            controller_down_s=1.0,
            slow_sockets=200,
            slow_hold_s=11.0,
        )


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
    badly_answered: int = 0
    """A 5xx other than 503, a 4xx or 503 without problem details, or a 429 or 503 without
    ``Retry-After``."""
    slowest_answer_s: float = 0.0

    def facts(self) -> str:
        answers = ", ".join(f"{n}×{status}" for status, n in sorted(self.statuses.items()))
        return (
            f"{self.uploads} uploads of {self.body_bytes / 2**20:.2f} MiB "
            f"({self.limit_bytes - self.body_bytes} B under the limit): {answers or 'none'}; "
            f"{self.unanswered} unanswered, {self.badly_answered} badly answered, slowest "
            f"{self.slowest_answer_s:.1f} s"
        )


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


class _Run:
    """One scenario's load (and sentinel), memory sampler and fault window; leaving the block
    without :meth:`finish` (the scenario raised) stops the load and the sampler at once, so
    nothing of it goes on into the next scenario."""

    def __init__(
        self,
        rig: Rig,
        timing: Timing,
        name: str,
        seed: int,
        *,
        sentinel: bool = False,
        key: str | None = None,
    ) -> None:
        self.rig = rig
        self.timing = timing
        self.name = name
        self.key = key or rig.new_key(f"load-{name}")
        self.sampler = RssSampler(rig.pids).start()
        self.load = Load(
            rig.controller_url,
            self.key,
            rig.targets,
            concurrency=timing.concurrency,
            first_seed=seed,
        ).start()
        self.sentinel = (
            Load(
                rig.controller_url,
                self.key,
                [rig.far_target],
                concurrency=1,
                options=SENTINEL_OPTIONS,
                first_seed=seed,
            ).start()
            if sentinel
            else None
        )
        self.fault_start = self.fault_end = 0.0
        self.outcomes: list[Outcome] = []
        """The load's and the sentinel's, once :meth:`finish` has run."""
        self._finished = False

    def __enter__(self) -> _Run:
        return self

    def __exit__(self, *exc_info: object) -> None:
        if not self._finished:
            self._finished = True
            for load in self._loads():
                load.halt(0.0)
            for load in self._loads():
                load.stop(0.0)
            self.sampler.stop()

    def _loads(self) -> list[Load]:
        return [self.load] + ([] if self.sentinel is None else [self.sentinel])

    def warm(self) -> None:
        """The load before the fault; with a sentinel, until one of its searches is under way."""
        time.sleep(self.timing.warm_s)
        if self.sentinel is None:
            return
        sentinel = self.sentinel
        with ControllerClient(self.rig.controller_url, api_key=self.key) as client:

            def under_way() -> bool:
                return any(len(client.get(i).iterations) >= 2 for i in sentinel.in_flight)

            wait_until(under_way, self.timing.recover_s, interval_s=0.05)

    def begin(self) -> float:
        self.fault_start = time.monotonic()
        return self.fault_start

    def end(self) -> float:
        self.fault_end = time.monotonic()
        return self.fault_end

    def finish(self) -> Measured:
        """After ``after_s`` more load, stop it and measure."""
        time.sleep(self.timing.after_s)
        for load in self._loads():
            load.halt(self.timing.drain_s)
        sentinel = [] if self.sentinel is None else self.sentinel.stop(self.timing.drain_s)
        outcomes = self.load.stop(self.timing.drain_s)
        peaks = self.sampler.stop()
        self._finished = True
        self.outcomes = [*outcomes, *sentinel]
        window = (self.fault_start, self.fault_end)
        before = [o for o in outcomes if o.ended_at is not None and o.ended_at < self.fault_start]
        return Measured(
            name=self.name,
            counts=count(self.outcomes),
            peak_rss_mib=peaks,
            p95_s=p95(latencies(outcomes, window)),
            baseline_p95_s=p95(latencies(before)),
            fault_s=self.fault_end - self.fault_start,
            errors=tuple(sorted({str(o.error) for o in self.outcomes if o.lost})),
        )


def _in_flight_at(outcomes: Sequence[Outcome], moment: float) -> list[Outcome]:
    """Searches the controller had taken, not ended at ``moment``. A search counts as taken
    from its first attempt: one still being refused then is not in flight, but none is (the
    faults start on a healthy stack)."""
    return [
        o
        for o in outcomes
        if o.search_id is not None
        and o.started_at < moment
        and (o.ended_at is None or o.ended_at > moment)
    ]


def replica_killed(rig: Rig, timing: Timing) -> ReplicaKilled:
    """SIGKILL the last renderer replica mid-load (its stage keeps another). Supervised
    (:meth:`Rig.supervising`), the supervisor starts it again; plain, it stays dead for
    ``degraded_s`` and is then started again on its port. The window ends when the broker
    counts it up again."""
    renderers = rig.replicas("renderer")
    if len(renderers) < 2:
        raise ValueError("killing a replica mid-load needs a stage with two replicas")
    victim = renderers[-1]
    name = "replica-killed-supervised" if rig.supervised else "replica-killed-plain"
    with _Run(rig, timing, name, seed=1000) as run:
        run.warm()
        started = run.begin()
        restarts = rig.restarts(victim.url)
        plan = rig.kill(victim)
        came_back = True
        try:
            if rig.supervised:
                wait_until(lambda: rig.restarts(victim.url) > restarts, timing.recover_s)
            else:
                time.sleep(timing.degraded_s)
                rig.restart(plan, timing.recover_s)
            wait_until(lambda: rig.replica_up(victim.url), timing.recover_s, interval_s=0.2)
        except TimeoutError:
            came_back = False
        back = run.end()
        served_then = rig.served(victim.url)
        measured = run.finish()
    return ReplicaKilled(
        measured,
        supervised=rig.supervised,
        killed="renderer",
        came_back=came_back,
        back_after_s=back - started,
        restarts=rig.restarts(victim.url) - restarts,
        served_after=rig.served(victim.url) - served_then,
    )


def replica_killed_supervised(rig: Rig, timing: Timing) -> ReplicaKilled:
    """:func:`replica_killed` under ``cosmos up``'s supervision."""
    with rig.supervising():
        return replica_killed(rig, timing)


def _budget_s(rig: Rig) -> float:
    default = ControllerSettings.model_fields["controller_outage_budget_s"].default
    return float(rig.setting("COSMOS_CONTROLLER_OUTAGE_BUDGET_S", str(default)))


def detector_outage(rig: Rig, timing: Timing) -> DetectorOutage:
    """Every detector replica SIGKILLed mid-load, started again ``outage_s`` later on its port.
    Searches in flight wait (the controller's outage budget must be longer than the outage);
    submissions meanwhile are refused with 503 and asked again. The window ends when the
    controller's ``/health`` says ok again."""
    if rig.supervised:
        raise ValueError("a supervisor would start the detector again at once")
    if _budget_s(rig) <= timing.outage_s:
        raise ValueError(
            f"an outage of {timing.outage_s:g} s needs an outage budget longer than it "
            f"(COSMOS_CONTROLLER_OUTAGE_BUDGET_S is {_budget_s(rig):g})"
        )
    with _Run(rig, timing, "detector-outage", seed=2000, sentinel=True) as run:
        run.warm()
        down = run.begin()
        plans = [rig.kill(process) for process in rig.replicas("detector")]
        degraded_seen = False
        while time.monotonic() < down + timing.outage_s:
            health = rig.health() or {}
            if health.get("status") == "degraded" and "detector" in health["unavailable_stages"]:
                degraded_seen = True
            time.sleep(0.25)
        restarted = time.monotonic()
        for plan in plans:
            rig.restart(plan, timing.recover_s)
        wait_until(lambda: (rig.health() or {}).get("status") == "ok", timing.recover_s)
        back = run.end()
        measured = run.finish()
    in_flight = _in_flight_at(run.outcomes, down)
    return DetectorOutage(
        measured,
        outage_s=restarted - down,
        degraded_seen=degraded_seen,
        recovered_after_s=back - restarted,
        in_flight=len(in_flight),
        ridden_out=sum(o.succeeded and (o.ended_at or 0.0) > restarted for o in in_flight),
    )


def _listed(url: str, key: str) -> dict[str, str]:
    """Every search the key's ``GET /searches`` lists: id → status."""
    found: dict[str, str] = {}
    with httpx.Client(base_url=url, timeout=30.0, headers=_bearer(key)) as client:
        while True:
            page = client.get("/searches", params={"limit": 200, "offset": len(found)})
            page.raise_for_status()
            body = page.json()
            found.update({item["id"]: item["status"] for item in body["items"]})
            if not body["items"] or len(found) >= body["total"]:
                return found


def _bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def controller_killed(rig: Rig, timing: Timing) -> ControllerKilled:
    """SIGKILL the controller mid-load; start it again on its port and database
    ``controller_down_s`` later. Its clients meanwhile get no answer and ask again; it resumes
    the queued and running searches from their recorded iterations. The window ends when it is
    healthy again."""
    if rig.supervised:
        raise ValueError("this scenario restarts the controller itself, not a supervisor")
    with _Run(rig, timing, "controller-killed", seed=3000, sentinel=True) as run:
        run.warm()
        killed = run.begin()
        (controller,) = rig.replicas("controller")
        plan = rig.kill(controller)
        time.sleep(timing.controller_down_s)
        rig.restart(plan, timing.recover_s)
        back = run.end()
        measured = run.finish()
    in_flight = _in_flight_at(run.outcomes, killed)
    known = {o.search_id for o in run.outcomes}
    orphans = {i: s for i, s in _listed(rig.controller_url, run.key).items() if i not in known}
    return ControllerKilled(
        measured,
        down_s=back - killed,
        in_flight=len(in_flight),
        resumed=sum(o.succeeded and (o.ended_at or 0.0) > back for o in in_flight),
        orphans=len(orphans),
        orphans_unfinished=sum(s not in TERMINAL_STATUSES for s in orphans.values()),
    )


def _address(url: str) -> tuple[str, int]:
    host, port = url.removeprefix("http://").split(":")
    return host, int(port)


def slow_clients(rig: Rig, timing: Timing) -> SlowClients:
    """``slow_sockets`` connections to the controller (loopback only) that send part of a
    request head and then nothing (one in ten sends nothing at all, one in ten trickles a byte a
    second), held for ``slow_hold_s`` once all are open, while the load runs and ``GET /health``
    is asked every 0.2 s on a new connection. The window ends with the hold; by then the server
    should have closed every one of them (its head deadline is 10 s)."""
    host, port = _address(rig.controller_url)
    if host not in {"127.0.0.1", "localhost", "::1"}:
        raise ValueError("slow clients are sent to a loopback address only")
    if not 0 < timing.slow_sockets <= MAX_SLOW_SOCKETS:
        raise ValueError(f"slow_sockets must be 1..{MAX_SLOW_SOCKETS}")
    with _Run(rig, timing, "slow-clients", seed=4000) as run:
        run.warm()
        run.begin()
        sockets: list[socket.socket] = []
        checks: list[float | None] = []  # seconds per /health answered 200, None otherwise
        holding = threading.Event()
        holding.set()

        def trickle(slow: list[socket.socket]) -> None:
            while holding.is_set():
                for sock in slow:
                    try:
                        sock.send(b"a")
                    except OSError:
                        pass
                time.sleep(1.0)

        def probe() -> None:
            while holding.is_set():
                asked = time.perf_counter()
                try:
                    ok = httpx.get(f"{rig.controller_url}/health", timeout=5.0).status_code == 200
                except httpx.TransportError:
                    ok = False
                checks.append(time.perf_counter() - asked if ok else None)
                time.sleep(0.2)

        try:
            for i in range(timing.slow_sockets):
                sock = socket.create_connection((host, port), timeout=5.0)
                sockets.append(sock)
                if i % 10:
                    sock.sendall(HALF_HEAD)
            threads = [
                threading.Thread(target=trickle, args=(sockets[5::10],), daemon=True),
                threading.Thread(target=probe, daemon=True),
            ]
            for thread in threads:
                thread.start()
            time.sleep(timing.slow_hold_s)
            holding.clear()
            for thread in threads:
                thread.join()
            closed = sum(_closed(sock) for sock in sockets)
        finally:
            holding.clear()
            for sock in sockets:
                sock.close()
        run.end()
        measured = run.finish()
    answered = [seconds for seconds in checks if seconds is not None]
    return SlowClients(
        measured,
        sockets=len(sockets),
        closed_by_server=closed,
        health_checks=len(checks),
        health_failures=len(checks) - len(answered),
        health_p95_s=p95(answered),
    )


def _closed(sock: socket.socket) -> bool:
    """Whether the server has closed the connection (after a 408 or without a word)."""
    sock.setblocking(False)
    try:
        while sock.recv(65536):
            pass  # the 408 it sent first
    except BlockingIOError:
        return False  # nothing more to read, and still open
    except OSError:
        return True  # reset
    return True


def maximal_upload_body(target: Target, limit_bytes: int, max_pixels: int, max_side: int) -> bytes:
    """A valid image of the target's view just under ``limit_bytes``: the target scaled up
    (same aspect) to the largest binary PPM that fits, ``P6`` header plus 3 bytes a pixel, so
    nothing compresses it, within the controller's caps of ``max_pixels`` and ``max_side``."""
    rgb = decode_image(target.image, max_pixels=1 << 24, max_side=1 << 14)
    height, width = rgb.shape[:2]
    pixels = min((limit_bytes - 32) // 3, max_pixels)
    new_width = min(int((pixels * width / height) ** 0.5), max_side)
    new_height = min(pixels // new_width, max_side)
    scaled = cv2.resize(rgb, (new_width, new_height), interpolation=cv2.INTER_LINEAR)
    body = encode_ppm(np.ascontiguousarray(scaled))
    if len(body) > limit_bytes:
        raise RuntimeError(f"{len(body)} bytes do not fit under {limit_bytes}")
    return body


def _controller_setting(rig: Rig, name: str) -> int:
    """The controller's integer setting ``controller_<name>`` as the rig runs it."""
    default = ControllerSettings.model_fields[f"controller_{name}"].default
    return int(rig.setting(f"COSMOS_CONTROLLER_{name.upper()}", str(default)))


def maximal_uploads(rig: Rig, timing: Timing) -> MaximalUploads:
    """``uploads`` clients of one tenant key each send a maximal target
    (:func:`maximal_upload_body`) at once, while the load runs. Every upload must get an answer:
    202, or a 4xx problem, or 503 with ``Retry-After``; never another 5xx or none. The searches
    the uploads started are cancelled once all are answered (they are not the load). The
    window runs from the first upload to the last answer; the controller's peak memory is the
    figure to watch."""
    limit = _controller_setting(rig, "max_upload_bytes")
    body = maximal_upload_body(
        rig.targets[0],
        limit,
        _controller_setting(rig, "max_image_pixels"),
        _controller_setting(rig, "max_image_side"),
    )
    uploader = rig.new_key("uploads")
    with _Run(rig, timing, "maximal-uploads", seed=5000) as run:
        run.warm()
        started = run.begin()
        ready = threading.Barrier(timing.uploads)
        answers: list[tuple[int | None, bool, float, str | None]] = []

        with httpx.Client(
            base_url=rig.controller_url,
            timeout=httpx.Timeout(timing.upload_timeout_s, connect=10.0),
            limits=httpx.Limits(max_connections=timing.uploads),
            headers={**_bearer(uploader), "Content-Type": PPM_MEDIA_TYPE},
        ) as client:

            def upload(_: int) -> tuple[int | None, bool, float, str | None]:
                ready.wait(timeout=timing.upload_timeout_s)
                try:
                    response = client.post("/searches", content=body, params={"scene": "demo"})
                except httpx.TransportError:
                    return None, False, time.monotonic() - started, None
                return (
                    response.status_code,
                    well_answered(response),
                    time.monotonic() - started,
                    response.json().get("id") if response.status_code == 202 else None,
                )

            with ThreadPoolExecutor(timing.uploads) as pool:
                answers = list(pool.map(upload, range(timing.uploads)))
            run.end()
            for _, _, _, search_id in answers:
                if search_id is not None:
                    client.delete(f"/searches/{search_id}")
        measured = run.finish()
    statuses: dict[int, int] = {}
    for status, _, _, _ in answers:
        if status is not None:
            statuses[status] = statuses.get(status, 0) + 1
    return MaximalUploads(
        measured,
        uploads=timing.uploads,
        body_bytes=len(body),
        limit_bytes=limit,
        statuses=statuses,
        unanswered=sum(status is None for status, _, _, _ in answers),
        badly_answered=sum(status is not None and not good for status, good, _, _ in answers),
        slowest_answer_s=max((seconds for _, _, seconds, _ in answers), default=0.0),
    )


def well_answered(response: httpx.Response) -> bool:
    """202, or a problem (4xx, or 503 with ``Retry-After``; 429 with it too)."""
    status = response.status_code
    if status == 202:
        return True
    if not (400 <= status < 500 or status == 503):
        return False
    problem = response.headers.get("content-type", "").startswith(PROBLEM_JSON)
    return problem and (status not in {429, 503} or "retry-after" in response.headers)


class _Peeker:
    """One tenant's requests for another's searches, counting those that are not hidden as an
    unknown id is (a 404 of the same type and title)."""

    def __init__(self, url: str, key: str) -> None:
        self._client = httpx.Client(base_url=url, timeout=30.0, headers=_bearer(key))
        unknown = self._client.get("/searches/no-such-search").json()
        self._unknown = (unknown["type"], unknown["title"])
        self.requests = 0
        self.seen = 0

    def __enter__(self) -> _Peeker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._client.close()

    def peek(self, search_id: str, *methods: str) -> None:
        for method in methods:
            answer = self._client.request(method, f"/searches/{search_id}")
            body = answer.json()
            hidden = answer.status_code == 404 and (body.get("type"), body.get("title")) == (
                self._unknown
            )
            self.requests += 1
            self.seen += not hidden


def tenants(rig: Rig, timing: Timing) -> Tenants:
    """Two tenant keys, A (the load) and B (one client of its own), search side by side. Mid-load
    B asks for and tries to cancel A's searches in flight, and A asks for B's; afterwards each
    asks for every search of the other, B tries to cancel each of A's, and both list theirs.
    Every such request must be a 404 like an unknown id's, and no list may hold the other's."""
    key_a, key_b = rig.new_key("tenant-a"), rig.new_key("tenant-b")
    with _Run(rig, timing, "tenants", seed=6000, key=key_a) as run, ExitStack() as stack:
        other = Load(rig.controller_url, key_b, rig.targets, concurrency=1, first_seed=6500)
        stack.callback(other.halt, 0.0)
        other.start()
        b_peeks = stack.enter_context(_Peeker(rig.controller_url, key_b))
        a_peeks = stack.enter_context(_Peeker(rig.controller_url, key_a))
        run.warm()
        run.begin()
        deadline = time.monotonic() + max(timing.after_s, 2.0)
        while time.monotonic() < deadline:  # while searches of both run
            for search_id in run.load.in_flight:
                b_peeks.peek(search_id, "GET", "DELETE")
            for search_id in other.in_flight:
                a_peeks.peek(search_id, "GET")
            time.sleep(0.1)
        run.end()
        measured = run.finish()
        theirs = other.stop(timing.drain_s)
        ids_a = {o.search_id for o in run.outcomes if o.search_id is not None}
        ids_b = {o.search_id for o in theirs if o.search_id is not None}
        for search_id in ids_a:
            b_peeks.peek(search_id, "GET", "DELETE")
        for search_id in ids_b:
            a_peeks.peek(search_id, "GET")
    listed_a, listed_b = _listed(rig.controller_url, key_a), _listed(rig.controller_url, key_b)
    everyone = [*run.outcomes, *theirs]
    return Tenants(
        replace(
            measured,
            counts=count(everyone),
            errors=tuple(sorted({str(o.error) for o in everyone if o.lost})),
        ),
        a_searches=len(ids_a),
        b_searches=len(ids_b),
        checks=b_peeks.requests + a_peeks.requests + 2,
        b_saw_a=b_peeks.seen + len(ids_a & listed_b.keys()),
        a_saw_b=a_peeks.seen + len(ids_b & listed_a.keys()),
        b_lists_own=ids_b <= listed_b.keys(),
    )


Scenario = Callable[[Rig, Timing], ScenarioResult]

SCENARIOS: Final[Mapping[str, Scenario]] = {
    "tenants": tenants,
    "replica-killed-supervised": replica_killed_supervised,
    "replica-killed-plain": replica_killed,
    "detector-outage": detector_outage,
    "controller-killed": controller_killed,
    "slow-clients": slow_clients,
    "maximal-uploads": maximal_uploads,
}
"""Every scenario by name, in the order they run on one stack (the uploads last: they leave the
most behind)."""


def run_scenarios(
    workdir: Path,
    timing: Timing,
    names: Sequence[str] | None = None,
    env: Mapping[str, str] | None = None,
) -> Iterator[ScenarioResult | ScenarioFailure]:
    """Run the scenarios ``names`` (all by default) in :data:`SCENARIOS`' order on one rig in
    ``workdir`` (with ``env``), yielding each result as it comes; a scenario that raises yields
    a :class:`ScenarioFailure` and the rest go on."""
    chosen = list(SCENARIOS) if names is None else list(names)
    unknown = [name for name in chosen if name not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenarios {unknown}: choose from {list(SCENARIOS)}")
    with fault_rig(workdir, env=env) as rig:
        for name in (name for name in SCENARIOS if name in chosen):
            try:
                yield SCENARIOS[name](rig, timing)
            except Exception as exc:  # one scenario's failure is its row, not the run's end
                yield ScenarioFailure(name, f"{type(exc).__name__}: {exc}")
