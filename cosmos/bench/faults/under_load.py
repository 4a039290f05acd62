"""How every fault scenario runs: :class:`Timing` (how long and how hard), :class:`UnderLoad` (the
normal searches of a tenant key, with a sentinel where a search must be in flight across the
fault, the memory sampler, the fault's window) and what the controller says of a key's searches.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import httpx

from cosmos.bench.faults.harness import (
    Load,
    Outcome,
    RssSampler,
    count,
    latencies,
    p95,
)
from cosmos.bench.faults.results import Measured
from cosmos.bench.faults.rig import Rig, wait_until
from services.common.auth import bearer
from services.controller.client import ControllerClient

__all__ = ["SENTINEL_EARLY", "SENTINEL_OPTIONS", "Timing", "UnderLoad", "in_flight_at", "listed"]

SENTINEL_OPTIONS: Final[Mapping[str, Any]] = {
    "strategy": "simple",
    "start_theta_deg": 7.5,
    "start_phi_deg": 0.0,
    "max_iterations": 80,
}
SENTINEL_EARLY: Final = 4
"""A fault strikes while a sentinel search has done 2 to this many of its 12 iterations: with
only "at least 2" it could be at its 11th, end before the fault bit, and leave no search to
ride the fault out (a detector outage once measured 3 searches in flight, none waiting)."""


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


class UnderLoad:
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

    def __enter__(self) -> UnderLoad:
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
        """The load before the fault; with a sentinel, until one of its searches is under way
        and far from done (:data:`SENTINEL_EARLY`)."""
        time.sleep(self.timing.warm_s)
        if self.sentinel is None:
            return
        sentinel = self.sentinel
        with ControllerClient(self.rig.controller_url, api_key=self.key) as client:

            def under_way() -> bool:
                done = (len(client.get(i).iterations) for i in sentinel.in_flight)
                return any(2 <= n <= SENTINEL_EARLY for n in done)

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


def in_flight_at(outcomes: Sequence[Outcome], moment: float) -> list[Outcome]:
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


def listed(url: str, key: str) -> dict[str, str]:
    """Every search the key's ``GET /searches`` lists: id → status."""
    found: dict[str, str] = {}
    with httpx.Client(base_url=url, timeout=30.0, headers=bearer(key)) as client:
        while True:
            page = client.get("/searches", params={"limit": 200, "offset": len(found)})
            page.raise_for_status()
            body = page.json()
            found.update({item["id"]: item["status"] for item in body["items"]})
            if not body["items"] or len(found) >= body["total"]:
                return found
