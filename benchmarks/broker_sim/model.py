"""The broker in a discrete-event simulation (SimPy): replicas, their queues, the broker's calls.

Each replica serves its tasks one at a time, first come first served (a renderer renders on one
thread, and a detector's or an optimizer's work holds its process's CPU), a task of measured
length ``d`` taking ``d / speed``; so a task's end is known when it is sent, after the tasks
queued there, :math:`e = \\max(t, e_{\\text{last}}) + d/s`, and a call is one timeout event (a
replica goes on with a task the broker gave up waiting for).

The broker is the live one's: the replica is chosen by
:func:`services.controller.placement.choose` (the project's heuristics) over the broker's own
:class:`~services.controller.placement.Replica` records, which learn what the live broker's do
(tasks in flight, the moving average of each call's duration, failures in a row, the cooldown,
``/health`` every ``health_interval_s`` bringing a replica back and reporting its queue). A call
is retried as :meth:`Broker.call <services.controller.broker.Broker.call>` retries: on a 5xx or
a timeout, on another replica, after ``backoff_s · 2^(attempt−1)``; a task no replica could serve
waits ``recovery_probe_s`` and is sent again. The broker's and the controller's defaults apply.

Two routers stand beside the heuristics, choosing among the same candidates (replicas not out
nor already tried for this task):

* ``power-of-two-choices`` (Ray Serve's default): two distinct candidates at random, the one with
  fewer tasks ahead (the broker's :attr:`~services.controller.placement.Replica.load`);
* ``oracle``: the candidate that would finish this task first, knowing every replica's true
  speed, queue and failure and the task's length: :math:`\\arg\\min_r \\max(t, f_r) + d/s_r`
  with :math:`f_r` when replica :math:`r`'s queue drains.
"""

from __future__ import annotations

import inspect
import itertools
import random
from collections import deque
from collections.abc import Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import simpy

from benchmarks.broker_sim.workload import SearchPlan
from services.controller.broker import Broker
from services.controller.placement import Heuristic, Replica, candidates, choose
from services.controller.settings import ControllerSettings

__all__ = [
    "DEFAULT_POLICY",
    "ORACLE",
    "P2C",
    "POLICIES",
    "Outcome",
    "ReplicaSpec",
    "latency_stats",
    "simulate",
]

P2C: Final = "power-of-two-choices"
ORACLE: Final = "oracle"
POLICIES: Final = (*(h.value for h in Heuristic), P2C, ORACLE)
DEFAULT_POLICY: Final = str(ControllerSettings.model_fields["controller_broker_heuristic"].default)
KINDS: Final = {"renderer": "render", "detector": "detect", "optimizer": "optimize"}

_defaults = inspect.signature(Broker.__init__).parameters
MAX_ATTEMPTS: Final[int] = _defaults["max_attempts"].default
BACKOFF_S: Final[float] = _defaults["backoff_s"].default
FAILURE_THRESHOLD: Final[int] = _defaults["failure_threshold"].default
COOLDOWN_S: Final[float] = _defaults["cooldown_s"].default
HEALTH_INTERVAL_S: Final[float] = _defaults["health_interval_s"].default
RECOVERY_PROBE_S: Final[float] = _defaults["recovery_probe_s"].default
TIMEOUTS_S: Final = ControllerSettings.model_construct().timeouts()  # defaults, not the env

Process = Generator[simpy.Event, Any, Any]


@dataclass(frozen=True)
class ReplicaSpec:
    """A simulated replica's true nature: its speed, and whether its tasks fail (after
    ``fail_ms``; its ``/health`` still answers, so the broker keeps taking it back)."""

    speed: float
    failing: bool = False
    fail_ms: float = 5.0


@dataclass
class _Server:
    """A replica's queue, first come first served: when each task sent to it ends (s)."""

    spec: ReplicaSpec
    ends: deque[float] = field(default_factory=deque)

    def finish_s(self, now: float, length_ms: float) -> float:
        """When a task of ``length_ms`` sent now would end: after those queued, at its speed."""
        free_at = self.ends[-1] if self.ends else now
        return max(now, free_at) + length_ms / self.spec.speed / 1000.0

    def take(self, now: float, length_ms: float) -> float:
        """Queue a task; when it ends."""
        end = self.finish_s(now, length_ms)
        self.ends.append(end)
        return end

    def queued(self, now: float) -> int:
        """Tasks not yet done (those the broker gave up on by a timeout included)."""
        while self.ends and self.ends[0] <= now:
            self.ends.popleft()
        return len(self.ends)


@dataclass
class Outcome:
    """What one run measured: each search's latency (s) and how often, and the calls' faults."""

    policy: str
    latency_s: dict[int, float] = field(default_factory=dict)
    completions: dict[int, int] = field(default_factory=dict)
    span_s: float = 0.0
    failed_calls: int = 0
    timeouts: int = 0


class _Sim:
    def __init__(
        self,
        policy: str,
        pools: Mapping[str, Sequence[ReplicaSpec]],
        plans: Sequence[SearchPlan],
        seed: int,
    ) -> None:
        if policy not in POLICIES:
            raise ValueError(f"unknown policy {policy!r}; one of {', '.join(POLICIES)}")
        self.env = simpy.Environment()
        self.policy = policy
        self.plans = plans
        self.rng = random.Random(seed)
        self.replicas: dict[str, list[Replica]] = {}
        self.servers: dict[str, _Server] = {}
        for stage, specs in pools.items():
            self.replicas[stage] = []
            for number, spec in enumerate(specs, 1):
                url = f"sim://{stage}-{number}"
                self.replicas[stage].append(Replica(stage=stage, url=url, name=f"{stage}-{number}"))
                self.servers[url] = _Server(spec)
        self.turns = {stage: itertools.count() for stage in pools}
        self.outcome = Outcome(policy)
        self.all_done = self.env.event()

    # -- the choice -----------------------------------------------------------------------

    def pick(self, stage: str, length_ms: float, tried: set[str]) -> Replica:
        pool, now = self.replicas[stage], self.env.now
        if self.policy == P2C:
            among = candidates(pool, now, tried)
            if len(among) == 1:
                return among[0]
            first, second = self.rng.sample(among, 2)
            return first if first.load <= second.load else second
        if self.policy == ORACLE:
            among = candidates(pool, now, tried)
            working = [r for r in among if not self.servers[r.url].spec.failing] or among
            return min(working, key=lambda r: self.servers[r.url].finish_s(now, length_ms))
        turn = next(self.turns[stage])
        return choose(Heuristic(self.policy), pool, KINDS[stage], turn=turn, now=now, exclude=tried)

    # -- a replica, a call, a search --------------------------------------------------------

    def call(self, stage: str, length_ms: float) -> Process:
        """The broker's side of one task, retried as :meth:`Broker.call` retries."""
        pool, kind, timeout_s = self.replicas[stage], KINDS[stage], TIMEOUTS_S[stage]
        while True:
            tried: set[str] = set()
            for attempt in range(MAX_ATTEMPTS):
                if attempt:
                    yield self.env.timeout(BACKOFF_S * 2 ** (attempt - 1))
                if len(tried) == len(pool):
                    tried.clear()
                replica = self.pick(stage, length_ms, tried)
                replica.in_flight += 1
                sent = self.env.now
                server = self.servers[replica.url]
                if server.spec.failing:
                    yield self.env.timeout(server.spec.fail_ms / 1000.0)
                    answered = False
                else:  # the replica's queue says when it ends: no need to simulate its steps
                    wait_s = server.take(sent, length_ms) - sent
                    yield self.env.timeout(min(wait_s, timeout_s))
                    answered = wait_s <= timeout_s
                    self.outcome.timeouts += (
                        not answered
                    )  # the replica goes on with it all the same
                replica.in_flight -= 1
                if answered:
                    replica.succeeded(kind, (self.env.now - sent) * 1000.0)
                    return
                self.outcome.failed_calls += 1
                replica.failed_at(self.env.now, FAILURE_THRESHOLD, COOLDOWN_S)
                tried.add(replica.url)
            yield self.env.timeout(RECOVERY_PROBE_S)

    def search(self, plan: SearchPlan) -> Process:
        started = self.env.now
        target = self.env.process(self.call("detector", plan.target_ms))
        for i, optimize_ms in enumerate(plan.optimize_ms):
            if i < len(plan.render_ms):  # later iterations are at poses seen before
                yield from self.call("renderer", plan.render_ms[i])
                yield from self.call("detector", plan.detect_ms[i])
            if i == 0:
                yield target
            yield from self.call("optimizer", optimize_ms)
        self.outcome.latency_s[plan.number] = self.env.now - started
        self.outcome.completions[plan.number] = self.outcome.completions.get(plan.number, 0) + 1
        if len(self.outcome.completions) == len(self.plans):
            self.all_done.succeed()

    def arrive(self) -> Process:
        for plan in self.plans:
            if plan.arrival_s > self.env.now:
                yield self.env.timeout(plan.arrival_s - self.env.now)
            self.env.process(self.search(plan))

    def probe(self) -> Process:
        """``/health`` of every replica every ``HEALTH_INTERVAL_S``: all answer, with their
        queue (tasks the broker gave up on by a timeout included)."""
        while True:
            yield self.env.timeout(HEALTH_INTERVAL_S)
            for pool in self.replicas.values():
                for replica in pool:
                    replica.answered_health(float(self.servers[replica.url].queued(self.env.now)))

    def run(self) -> Outcome:
        self.env.process(self.arrive())
        self.env.process(self.probe())
        self.env.run(until=self.all_done)
        first = min(plan.arrival_s for plan in self.plans)
        self.outcome.span_s = self.env.now - first
        return self.outcome


def simulate(
    policy: str,
    pools: Mapping[str, Sequence[ReplicaSpec]],
    plans: Sequence[SearchPlan],
    seed: int = 0,
) -> Outcome:
    """Run ``plans`` through replicas ``pools`` (stage -> replicas) with the broker choosing by
    ``policy`` (a heuristic's name, :data:`P2C` or :data:`ORACLE`); ``seed`` drives p2c's draws."""
    if not plans:
        raise ValueError("no search to simulate")
    return _Sim(policy, pools, plans, seed).run()


def latency_stats(outcome: Outcome) -> dict[str, float]:
    """p50, p99 and mean search latency (ms) and throughput (searches/s) of a run."""
    latencies = np.fromiter(outcome.latency_s.values(), dtype=float) * 1000.0
    return {
        "p50_ms": float(np.percentile(latencies, 50)),
        "p99_ms": float(np.percentile(latencies, 99)),
        "mean_ms": float(latencies.mean()),
        "per_s": len(latencies) / outcome.span_s if outcome.span_s > 0 else float("nan"),
    }
