"""Hosts of their own, shared (issue 24): two controllers sharing PostgreSQL, PostgreSQL, two
renderers, two detectors and an optimizer, each in a network namespace with its own address,
configured only by addresses, the controllers' leases short (:data:`LEASE_S`). Under a bounded
load of searches, submitted to both controllers:

1. a renderer host's link is cut while it renders for a search (``ip link set … down``);
2. latency and loss are put on the link of a detector host that carries detections;
3. both links are healed;
4. controller-1 is SIGKILLed while it runs searches: controller-2 takes them over within the
   lease time (plus its claim period), from their last recorded iteration; controller-1 is
   started again;
5. controller-2 is partitioned from PostgreSQL (and nothing else) for two leases: its probes
   still answer at once (``/livez`` 200, ``/readyz`` 503: its event loop never waits for the
   database), its runs pause and write nothing, controller-1 takes them over within the lease
   time; then the partition heals, and controller-2's stale writes are refused (fencing).

It prints its counts and asserts them: no search lost, no iteration written twice (a trigger in
the database logs every write of an iteration: :mod:`tests.hosts.database`), every search
answered, and by either controller.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest

from services.controller.readiness import PROBE_TIMEOUT_S
from tests.hosts.cluster import CONTROLLER, Cluster, HostSpec
from tests.hosts.database import Ledger, start_postgres
from tests.hosts.load import Searches
from tests.hosts.network import Host, Network
from tests.hosts.test_hosts import CONTROLLER_ENV as ONE_CONTROLLER_ENV
from tests.hosts.test_hosts import SEARCH, TARGETS, render_targets
from tests.hosts.test_hosts import TOPOLOGY as ONE_CONTROLLER
from tests.support import skip_unless_on_ci

pytestmark = [pytest.mark.hosts, pytest.mark.slow]

TOPOLOGY = (
    HostSpec("controller-1", CONTROLLER),
    HostSpec("controller-2", CONTROLLER),
    *(spec for spec in ONE_CONTROLLER if spec.role is not CONTROLLER),  # the same stages
)
LEASE_S = 3.0
TAKEOVER_S = 40 * LEASE_S
"""Orphaned searches are taken over once their lease lapses: on an idle machine within the
lease, a claim period and the poll that sees it (~4-6 s, which the test prints). Neither the
killed nor the partitioned controller can give them up, so any takeover is the lease's: this
only bounds the wait for one, which tells a takeover from none. How fast it comes is a figure
the test prints (docs/EVALUATION.md records it), not a bound it asserts: with both cores busy
beside the test (training a detector, a bench, CI) takeovers took 13.7, 14.7 and 47 s."""
RENDER_TIMEOUT_S = 6.0
CONTROLLER_ENV = {
    "COSMOS_CONTROLLER_LEASE_S": str(LEASE_S),
    "COSMOS_CONTROLLER_RENDER_TIMEOUT_S": str(RENDER_TIMEOUT_S),
    # either controller can take all the other's searches over at once
    "COSMOS_CONTROLLER_MAX_CONCURRENT_SEARCHES": "10",
    "COSMOS_CONTROLLER_QUOTA_ACTIVE_SEARCHES": "20",
    "COSMOS_CONTROLLER_VIEW_WIDTH": "160",
    "COSMOS_CONTROLLER_VIEW_SPP": ONE_CONTROLLER_ENV["COSMOS_CONTROLLER_VIEW_SPP"],
}
DELAY_MS, LOSS = 50.0, 0.05
PROGRESS = 4  # iterations recorded under a fault before the next step
LIVEZ_S = 1.0  # what /livez of the partitioned controller may take at most
READYZ_S = PROBE_TIMEOUT_S + 1.0  # /readyz waits for the database that long, then says no


@pytest.fixture
def shared(network: Network, tmp_path: Path, say) -> tuple[Cluster, Host, Ledger]:
    """PostgreSQL on a host of its own, then the topology on it; the ledger logs every
    iteration written."""
    started = start_postgres(network)
    if isinstance(started, str):
        skip_unless_on_ci(started, "the shared hosts test")
    database, url = started
    cluster = Cluster(
        network, TOPOLOGY, tmp_path, database_url=url, controller_env=CONTROLLER_ENV
    ).start()
    ledger = Ledger(url)
    ledger.record_writes()
    say(f"PostgreSQL on {database.address} and {len(TOPOLOGY)} hosts up")
    return cluster, database, ledger


class Probes:
    """``/livez`` and ``/readyz`` of the controller at ``url``, asked one after the other on a
    thread of their own while the block runs: (path, status (0: no answer in 10 s), seconds)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.seen: list[tuple[str, int, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._ask, daemon=True)

    def __enter__(self) -> Probes:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()

    def _ask(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10.0) as client:
            while not self._stop.is_set():
                for path in ("/livez", "/readyz"):
                    asked = time.monotonic()
                    try:
                        status = client.get(path).status_code
                    except httpx.TimeoutException:
                        status = 0
                    self.seen.append((path, status, time.monotonic() - asked))
                self._stop.wait(0.2)

    def statuses(self, path: str) -> set[int]:
        return {status for asked, status, _ in self.seen if asked == path}

    def slowest(self, path: str) -> float:
        return max(seconds for asked, _, seconds in self.seen if asked == path)


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=5.0).status_code == 200
    except httpx.TransportError:
        return False


def _log_lines(cluster: Cluster, name: str, words: str) -> int:
    logs = (cluster.workdir / "logs" / name).glob("*.log")
    return sum(line.count(words) for log in logs for line in log.read_text().splitlines())


def test_two_controllers_share_searches_through_a_cut_a_kill_a_partition_and_a_bad_link(
    shared, say
):
    cluster, database, ledger = shared
    images = render_targets(cluster)
    load = Searches(cluster.urls(CONTROLLER), cluster.headers)

    def submit(count: int, controllers: tuple[int, ...]) -> set[str]:
        ids = set()
        for k in range(count):
            n = len(load.truth)
            image, target = images[n % len(TARGETS)], TARGETS[n % len(TARGETS)]
            to = controllers[k % len(controllers)]
            ids.add(load.submit(image, target, {**SEARCH, "seed": n}, to))
        say(f"{len(load.truth)} searches submitted so far")
        return ids

    def ended() -> set[str]:
        return {i for i in load.truth if i not in load.unfinished}

    def pid(name: str) -> int:
        return cluster.process(name).process.pid

    def busy(controllers: tuple[int, ...]) -> None:
        """New searches on ``controllers`` when every search has ended: a wait for a moment
        inside a search must not outlast the searches (one-render searches end fast)."""
        if not load.unfinished:
            submit(2, controllers)

    def holding(name: str, controller: int) -> set[str]:
        """The unfinished searches the controller on ``name`` (``controller``) holds, once one
        of them has recorded iterations."""

        def seen_running() -> set[str]:
            busy((controller,))
            return {s.id for s in load.running if s.iterations} & ledger.held_by(pid(name))

        load.wait(seen_running, 60, f"{name} running searches", poll_s=0.1)
        return ledger.held_by(pid(name)) - ended()

    def taken_over(held: set[str], name: str, since: float) -> float:
        """Seconds from ``since`` until the controller on ``name`` holds ``held`` (or they
        ended)."""
        load.wait(
            lambda: held <= ledger.held_by(pid(name)) | ended(),
            TAKEOVER_S,
            f"{name} to take {len(held)} searches over",
            poll_s=0.1,
        )
        took = time.monotonic() - since
        say(f"{name} took them over {took:.1f} s later")
        return took

    try:
        submit(4, (0, 1))

        # 1. cut a renderer host's link while it renders for a search (either controller's)
        renderer = cluster.host("renderer-1")

        def in_flight() -> int:
            return max(int(load.replica("renderer-1", c)["in_flight"]) for c in (0, 1))

        def rendering_there() -> bool:
            busy((0, 1))
            return load.recorded >= 2 and in_flight() > 0

        load.wait(rendering_there, 60, "a render on renderer-1", poll_s=0.1)
        renderer.cut()
        cut_at, recorded, stranded = time.monotonic(), load.recorded, 0
        say(f"renderer-1 ({renderer.address}) cut with a render in flight")

        def carried_on() -> bool:
            nonlocal stranded
            busy((0, 1))
            stranded = max(stranded, in_flight())
            return (
                load.recorded >= recorded + PROGRESS
                and time.monotonic() > cut_at + RENDER_TIMEOUT_S + 1
            )

        load.wait(carried_on, 90, "progress with renderer-1 cut")

        # 2. latency and loss on the link of the detector controller-1 prefers now, with new
        # searches to carry detections over it (the first ones may have ended)
        submit(2, (0, 1))
        preferred = min(load.replicas("detector"), key=lambda r: r["expected_ms"].get("detect", 0))
        name = preferred["name"]
        served = sum(int(load.replica(name, c)["served"]) for c in (0, 1))
        detector = cluster.host(name)
        detector.impair(delay_ms=DELAY_MS, loss=LOSS)
        impaired_at, recorded = time.monotonic(), load.recorded
        say(f"{name} ({detector.address}): +{DELAY_MS:g} ms each way, {LOSS:.0%} loss")

        def detected_through_it() -> int:  # by either controller
            return sum(int(load.replica(name, c)["served"]) for c in (0, 1)) - served

        def went_on() -> bool:
            busy((0, 1))
            return (
                load.recorded >= recorded + PROGRESS
                and time.monotonic() > impaired_at + 3
                and (detected_through_it() > 0 or time.monotonic() > impaired_at + 15)
            )

        load.wait(went_on, 90, f"progress with {name} impaired")
        through_impaired = detected_through_it()

        # 3. heal both
        renderer.heal()
        detector.clear()
        say(f"links healed ({stranded} renders stranded, {through_impaired} detections slowed)")

        # 4. SIGKILL controller-1 while it runs searches; controller-2 takes them over
        submit(3, (0,))
        orphans = holding("controller-1", 0)  # waits for one with recorded iterations
        load.snapshot()  # after that wait, so the kill finds it running with them
        cluster.kill("controller-1")
        killed_at = time.monotonic()
        say(f"controller-1 killed holding {len(orphans)} unfinished searches")
        took_kill_s = taken_over(orphans, "controller-2", killed_at)
        cluster.restart("controller-1")

        # 5. partition controller-2 from PostgreSQL for two leases, then heal
        submit(3, (1,))
        cut_off = holding("controller-2", 1)
        controller_2 = cluster.host("controller-2")
        controller_2.partition(database)
        partitioned_at = time.monotonic()
        say(f"controller-2 partitioned from PostgreSQL holding {len(cut_off)} searches")
        with Probes(cluster.url("controller-2")) as probes:
            took_partition_s = taken_over(cut_off, "controller-1", partitioned_at)
            time.sleep(max(0.0, partitioned_at + 2 * LEASE_S - time.monotonic()))
        controller_2.rejoin(database)
        healed_at = time.monotonic()
        slowest = {path: probes.slowest(path) for path in ("/livez", "/readyz")}
        say(
            f"partition healed after {healed_at - partitioned_at:.1f} s; {len(probes.seen)} probes "
            f"of controller-2, the slowest /livez {slowest['/livez'] * 1000:.0f} ms, /readyz "
            f"{slowest['/readyz'] * 1000:.0f} ms"
        )
        load.wait(lambda: _ready(cluster.url("controller-2")), 30, "controller-2 ready again")
        say(f"controller-2 ready again {time.monotonic() - healed_at:.1f} s after the heal")

        load.wait(lambda: not load.unfinished, 150, "every search to end", poll_s=0.5)
        counts = load.counts()
        twice = ledger.written_twice()
        by_each = load.answered_by_each()
        fenced = _log_lines(cluster, "controller-2", "stopped here")
        paused = _log_lines(cluster, "controller-2", "stopped: COSMOS_CONTROLLER_DATABASE_URL")
        say(counts.line())
        say(
            f"iterations written {ledger.writes()}, written twice {len(twice)}; answered by "
            f"controller-1 {by_each[0]}, by controller-2 {by_each[1]}; taken over after the "
            f"kill in {took_kill_s:.1f} s, after the partition in {took_partition_s:.1f} s; "
            f"controller-2's runs stopped by the partition {paused}, by fencing after it {fenced}"
        )
    finally:
        load.close()
    assert stranded >= 1  # the cut struck renders in flight
    assert through_impaired >= 1  # the impaired link carried detections
    assert counts.lost == 0, load.states()
    assert counts.answered == counts.submitted == len(load.truth)
    assert counts.recorded_twice == 0
    assert twice == [], twice
    assert by_each == [counts.submitted, counts.submitted]
    assert orphans  # the kill struck running searches
    assert cut_off  # so did the partition
    assert counts.running_at_kill >= 1
    assert counts.resumed == counts.running_at_kill
    assert probes.statuses("/livez") == {200}
    assert 503 in probes.statuses("/readyz")
    assert slowest["/livez"] < LIVEZ_S, probes.seen
    assert slowest["/readyz"] < READYZ_S, probes.seen
    assert counts.found == counts.submitted
