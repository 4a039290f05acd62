"""Controllers sharing PostgreSQL: a search is run under one lease at a time; a controller that
stops beating loses its searches to another, which resumes them from the last recorded
iteration; the old owner's writes are refused when it comes back (fencing by generation).
Two stores on one database of the session's real server are two controllers."""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import pytest

from services.controller.events import Notifier
from services.controller.runner import SearchRunner
from services.controller.store import (
    Lease,
    LeaseLost,
    Leases,
    SearchStore,
    open_database,
    utcnow,
)
from tests.controller.test_database_faults import allow_connections
from tests.controller.test_retention import OUTAGE_ERROR
from tests.controller.test_runner import PNG, FakeStages
from tests.controller.test_store import iteration, search

LEASE_S = 0.6


@pytest.fixture
def url(postgres) -> str:
    return postgres.new_schema()


def test_one_lease_at_a_time_and_stale_writes_are_refused(url, opened):
    one, other = opened(url), opened(url)
    one.create(search("s"), b"x")
    mine, theirs = Leases(one.database, "A", LEASE_S), Leases(other.database, "B", LEASE_S)
    first = mine.take("s")
    assert first == Lease("s", 1)
    assert theirs.take("s") is None
    assert theirs.claim(10) == []
    one.update("s", first, status="running")
    one.add_iteration("s", iteration(0), first)

    time.sleep(LEASE_S + 0.1)  # A stops beating
    assert theirs.claim(10) == [Lease("s", 2)]
    with pytest.raises(LeaseLost):  # A comes back: its writes are refused, whole
        one.add_iteration("s", iteration(1), first, status="succeeded")
    with pytest.raises(LeaseLost):
        one.update("s", first, status="failed")
    assert mine.renew([first]) == []
    assert [it.index for it in other.iterations("s")] == [0]
    assert other.get("s").status == "running"
    second = Lease("s", 2)
    other.add_iteration("s", iteration(1), second)
    assert theirs.renew([second]) == [second]

    theirs.release(second)  # its run ended unfinished: claimable at once, never generation 2
    assert mine.claim(10) == [Lease("s", 3)]
    other.update("s", status="failed", error=OUTAGE_ERROR)  # through any: the holder hears
    assert mine.renew([Lease("s", 3)]) == []
    assert mine.claim(10) == []  # finished searches are not claimed
    mine.release(Lease("s", 3))  # its run stopped
    other.reopen("s")  # retried: a generation never handed out before
    assert theirs.take("s") == Lease("s", 4)


def test_a_search_recorded_with_its_lease_is_never_claimable(url, opened):
    """The submitting controller takes the lease in the transaction that records the search:
    another controller's claim, at any moment after the commit, finds nothing to take."""
    one, other = opened(url), opened(url)
    mine, theirs = Leases(one.database, "A", LEASE_S), Leases(other.database, "B", LEASE_S)
    assert one.create(search("s"), b"x", leases=mine) == Lease("s", 1)
    assert theirs.claim(10) == []
    assert theirs.take("s") is None
    assert mine.renew([Lease("s", 1)]) == [Lease("s", 1)]
    assert other.create(search("t"), b"y") is None  # without leases: claimable at once
    assert theirs.claim(10) == [Lease("t", 1)]


def test_controllers_claiming_at_once_never_share_a_search(url, opened):
    stores = [opened(url) for _ in range(3)]
    for n in range(30):
        stores[0].create(search(f"s{n:02d}", minutes=n), b"x")
    holders = [Leases(store.database, f"c{i}", 30.0) for i, store in enumerate(stores)]
    with ThreadPoolExecutor(3) as pool:
        claimed = list(pool.map(lambda leases: leases.claim(30), holders))
    ids = [lease.search_id for leases in claimed for lease in leases]
    assert sorted(ids) == [f"s{n:02d}" for n in range(30)]  # each exactly once
    assert all(lease.generation == 1 for leases in claimed for lease in leases)


class Recording(SearchStore):
    """A store that notes each iteration that was written (not refused), and by whom."""

    def __init__(self, url: str, name: str, landed: list[tuple[str, int]]) -> None:
        super().__init__(open_database(url))
        self.name = name
        self.landed = landed

    def add_iteration(self, search_id, iteration, lease=None, **changes):
        super().add_iteration(search_id, iteration, lease, **changes)
        self.landed.append((self.name, iteration.index))


class Gated(FakeStages):
    """Answers ``pause_after`` optimizer calls, then waits for ``gate``."""

    def __init__(self, detail, pause_after: int) -> None:
        super().__init__(detail)
        self.pause_after = pause_after
        self.gate = asyncio.Event()

    async def optimize(self, request, request_id=""):
        if self.calls["optimize"] >= self.pause_after:
            await self.gate.wait()
        return await super().optimize(request, request_id)


async def _until(condition, timeout_s: float = 10.0) -> float:
    """Seconds until ``condition()`` held (polled); fails after ``timeout_s``."""
    t0 = time.perf_counter()
    while not condition():
        if time.perf_counter() - t0 > timeout_s:
            raise AssertionError(f"not within {timeout_s} s")
        await asyncio.sleep(0.02)
    return time.perf_counter() - t0


@pytest.mark.anyio
async def test_a_controller_that_stops_beating_is_taken_over_and_fenced(
    url, detail, record_property
):
    landed: list[tuple[str, int]] = []
    a_store, b_store = Recording(url, "A", landed), Recording(url, "B", landed)
    record = search("s1").model_copy(update={"max_iterations": 6})
    a_store.create(
        record.model_copy(update={"start": FakeStages(detail).grid_pose(record.start.index)}), PNG
    )
    a_stages = Gated(detail, pause_after=2)
    a = SearchRunner(
        a_store, a_stages, Notifier(), 1, leases=Leases(a_store.database, "A", LEASE_S)
    )
    b_stages = FakeStages(detail)
    b = SearchRunner(
        b_store, b_stages, Notifier(), 1, leases=Leases(b_store.database, "B", LEASE_S)
    )
    try:
        await a.start()
        await _until(lambda: len(a_store.iterations("s1")) == 2)
        await b.start()
        await asyncio.sleep(2 * LEASE_S)  # A beats: B takes nothing
        assert b.running == 0
        assert a._heartbeat is not None
        a._heartbeat.cancel()  # A is cut off: no more heartbeats
        took = await _until(lambda: any(name == "B" for name, _ in landed))  # B's first write
        await _until(lambda: b_store.get("s1").status == "succeeded")
        a_stages.gate.set()  # A comes back, and writes the iteration it was on
        await _until(lambda: a.running == 0)
    finally:
        await a.close()
        await b.close()
        a_store.close()
        b_store.close()
    record_property("takeover_s", round(took, 3))  # in --junitxml
    assert took < LEASE_S * 4 / 3 + 1.0, f"taken over {took:.2f} s after (lease {LEASE_S} s)"
    assert [index for name, index in landed if name == "A"] == [0, 1]
    assert [index for name, index in landed if name == "B"] == [2, 3, 4, 5]
    assert set(Counter(index for _, index in landed).values()) == {1}  # none recorded twice
    reader = Recording(url, "C", [])
    final = reader.get("s1")
    reader.close()
    assert final is not None
    assert final.status == "succeeded"
    assert [it.index for it in final.iterations] == [0, 1, 2, 3, 4, 5]
    assert final.updated_at <= utcnow()


@pytest.mark.anyio
async def test_a_search_pauses_while_the_database_is_away_and_resumes(postgres, detail):
    """The database goes away between two iterations: the run stops where it was recorded,
    and once the database is back the search is claimed again and finished, nothing lost and
    nothing recorded twice."""
    url = postgres.new_database()
    landed: list[tuple[str, int]] = []
    store = Recording(url, "A", landed)
    record = search("s1").model_copy(update={"max_iterations": 6})
    store.create(
        record.model_copy(update={"start": FakeStages(detail).grid_pose(record.start.index)}), PNG
    )
    stages = Gated(detail, pause_after=2)
    runner = SearchRunner(store, stages, Notifier(), 1, leases=Leases(store.database, "A", LEASE_S))  # noqa: E501
    database = url.rsplit("/", 1)[1]
    try:
        await runner.start()
        await _until(lambda: len(store.iterations("s1")) == 2)
        allow_connections(postgres, database, allowed=False)
        try:
            stages.gate.set()
            await _until(lambda: runner.running == 0)  # its next write failed: it stopped
        finally:
            allow_connections(postgres, database, allowed=True)
        await _until(lambda: store.get("s1").status == "succeeded", timeout_s=20)
    finally:
        await runner.close()
        store.close()
    assert [index for _, index in landed] == [0, 1, 2, 3, 4, 5]


@pytest.mark.anyio
async def test_a_cancel_through_another_controller_stops_the_run(postgres, detail):
    """B cancels a search A runs: A hears of it at its next heartbeat, stops the run and
    writes nothing more; the search stays cancelled with what was recorded before."""
    url = postgres.new_schema()
    landed: list[tuple[str, int]] = []
    a_store, b_store = Recording(url, "A", landed), Recording(url, "B", landed)
    record = search("s1").model_copy(update={"max_iterations": 6})
    a_store.create(
        record.model_copy(update={"start": FakeStages(detail).grid_pose(record.start.index)}), PNG
    )
    a_stages = Gated(detail, pause_after=2)
    a = SearchRunner(
        a_store, a_stages, Notifier(), 1, leases=Leases(a_store.database, "A", LEASE_S)
    )
    b = SearchRunner(
        b_store, FakeStages(detail), Notifier(), 1, leases=Leases(b_store.database, "B", LEASE_S)
    )
    try:
        await a.start()
        await _until(lambda: len(a_store.iterations("s1")) == 2)  # A runs it
        await b.start()
        assert b.cancel("s1").status == "cancelled"
        stopped = await _until(lambda: a.running == 0)
        a_stages.gate.set()
        await asyncio.sleep(2 * LEASE_S)  # nobody claims a cancelled search
        assert b.running == a.running == 0
    finally:
        await a.close()
        await b.close()
        a_store.close()
        b_store.close()
    assert stopped < LEASE_S
    assert landed == [("A", 0), ("A", 1)]
    reader = Recording(url, "C", [])
    final = reader.get("s1")
    reader.close()
    assert final.status == "cancelled"
    assert [it.index for it in final.iterations] == [0, 1]


def test_writes_and_claims_of_one_search_at_once_end_in_one_owner(url, opened):
    """A holder writes while another controller claims the same search over and over (a lease
    that runs out at once): no deadlock, no error; the writes before the first takeover land,
    every later one is refused."""
    one, other = opened(url), opened(url)
    one.create(search("s"), b"x")
    lease = Leases(one.database, "A", 0.001).take("s")
    theirs = Leases(other.database, "B", 0.001)
    outcomes: Counter[str] = Counter()

    def write() -> None:
        for n in range(100):
            try:
                one.add_iteration("s", iteration(n), lease)
                outcomes["written"] += 1
            except LeaseLost:
                outcomes["refused"] += 1

    def claim() -> None:
        for _ in range(100):
            outcomes["claimed"] += len(theirs.claim(1))

    with ThreadPoolExecutor(2) as pool:
        for done in [pool.submit(write), pool.submit(claim)]:
            done.result()  # a deadlock or any other error raises here
    assert outcomes["written"] + outcomes["refused"] == 100
    assert outcomes["claimed"] >= 1
    assert [it.index for it in other.iterations("s")] == list(range(outcomes["written"]))
