"""Concurrent cancels, retries and takeovers of one search, through two controllers sharing
PostgreSQL, leave exactly one outcome: it is reopened once, run to one end, and a cancel that
arrives as it succeeds leaves the success whole (never "cancelled" with a result).

Each round starts from a search an outage failed, and lets loose at once, on threads (as two
controller processes would): a retry through each controller, a cancel through each, and a run
on each (take the lease, record iteration 1, succeed), each as the runner does it: read, check,
write."""

from __future__ import annotations

import random
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import pytest

from services.common.contracts.search import TERMINAL_STATUSES, SearchResult
from services.common.geometry.pose import Pose
from services.controller.outages import why_not_retryable
from services.controller.store import LeaseLost, Leases, SearchStore
from tests.controller.test_retention import OUTAGE_ERROR
from tests.controller.test_runner import PNG
from tests.controller.test_store import START, iteration, search

ROUNDS = 20
RESULT = SearchResult(
    pose=START, refined_pose=Pose(theta_deg=22.4, phi_deg=60.2), confidence=0.9, renders=2
)


@pytest.fixture
def url(postgres) -> str:
    return postgres.new_schema()


def _failed(store: SearchStore, leases: Leases, sid: str) -> None:
    store.create(search(sid), PNG)
    lease = leases.take(sid)
    store.add_iteration(sid, iteration(0), lease, status="running")
    store.update(sid, lease, status="failed", error=OUTAGE_ERROR)
    leases.release(lease)


def _round(stores: list[SearchStore], leases: list[Leases], sid: str) -> Counter[str]:
    """One round's six threads, let loose at once; what each did, counted."""
    done: Counter[str] = Counter()
    lock = threading.Lock()
    start = threading.Barrier(6)

    def count(what: str) -> None:
        with lock:
            done[what] += 1

    def retry(store: SearchStore) -> None:
        start.wait()
        seen = store.get(sid)
        if why_not_retryable(seen) is None and store.reopen(sid) is not None:
            count("reopened")

    def cancel(store: SearchStore) -> None:
        start.wait()
        time.sleep(random.uniform(0, 0.01))
        if store.get(sid).status not in TERMINAL_STATUSES:
            store.update(sid, status="cancelled")
            count("cancelled")

    def run(store: SearchStore, mine: Leases) -> None:
        start.wait()
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and store.get(sid).status != "cancelled":
            lease = mine.take(sid)
            if lease is None:
                time.sleep(0.002)
                continue
            try:
                store.update(sid, lease, status="running")
                time.sleep(random.uniform(0, 0.005))
                answer = {"status": "succeeded", "result": RESULT}
                store.add_iteration(sid, iteration(1), lease, **answer)
                count("iteration 1 written")
            except LeaseLost:
                count("refused")
            finally:
                mine.release(lease)

    with ThreadPoolExecutor(6) as pool:
        futures = [pool.submit(retry, store) for store in stores]
        futures += [pool.submit(cancel, store) for store in stores]
        futures += [pool.submit(run, s, m) for s, m in zip(stores, leases, strict=True)]
        for future in futures:
            future.result()  # an error or a deadlock raises here
    return done


def test_concurrent_cancels_retries_and_takeovers_leave_one_outcome(url, opened):
    stores = [opened(url), opened(url)]
    leases = [Leases(stores[0].database, "A", 30.0), Leases(stores[1].database, "B", 30.0)]
    for n in range(ROUNDS):
        sid = f"s{n}"
        _failed(stores[0], leases[0], sid)
        done = _round(stores, leases, sid)
        final = stores[1].get(sid)
        assert done["reopened"] == 1, (sid, done)
        assert done["iteration 1 written"] <= 1, (sid, done)
        assert final.status in {"succeeded", "cancelled"}, (sid, final.status, done)
        assert (final.result is not None) == (final.status == "succeeded"), (sid, final, done)
        assert [it.index for it in final.iterations] in ([0], [0, 1]), (sid, done)
