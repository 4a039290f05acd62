"""The sweep: every policy at every replica count, in each scenario, on the same searches.

Per scenario and size the replicas and the searches are drawn once (seeded by the scenario and
the size) and every policy serves exactly those: their differences are the routers' alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from benchmarks.broker_sim.model import (
    DEFAULT_POLICY,
    ORACLE,
    P2C,
    POLICIES,
    ReplicaSpec,
    latency_stats,
    simulate,
)
from benchmarks.broker_sim.workload import TaskLengths, arrivals, plan_searches, pool_sizes

__all__ = ["GOAL_ORACLE_RATIO", "SCENARIOS", "SweepConfig", "goal_met", "run_case", "sweep"]

SCENARIOS: Final = {
    "slow": "one replica per stage (of two or more) runs at ×0.1",
    "failing": "one replica per stage (of two or more) answers every task with a 5xx after 5 ms "
    "(its /health answers, so the broker takes it back after every cooldown)",
}
GOAL_ORACLE_RATIO: Final = 1.15
KIND_OF: Final = {"renderer": "render", "detector": "detect", "optimizer": "optimize"}


@dataclass(frozen=True)
class SweepConfig:
    """What the sweep simulates; the defaults are ``python -m benchmarks.broker_sim``'s."""

    sizes: tuple[int, ...] = (1, 2, 4, 8, 16, 32, 64, 128, 256)
    scenarios: tuple[str, ...] = tuple(SCENARIOS)
    policies: tuple[str, ...] = POLICIES
    searches: int = 2000
    load: float = 0.7
    """Mean arrival rate over the slowest stage's capacity (the odd replica's included)."""
    burst_share: float = 0.25
    """The share of searches that arrive in bursts, each as many searches as renderers."""
    speeds: tuple[float, float] = (0.5, 2.0)
    """Replica speeds are log-uniform in this range."""
    slow_speed: float = 0.1
    seed: int = 24


def replicas(
    config: SweepConfig, scenario: str, sizes: dict[str, int], rng: np.random.Generator
) -> dict[str, list[ReplicaSpec]]:
    """Each stage's replicas: log-uniform speeds, and the scenario's odd one where there are
    two or more."""
    low, high = np.log(config.speeds)
    pools = {}
    for stage, n in sizes.items():
        specs = [ReplicaSpec(speed=float(s)) for s in np.exp(rng.uniform(low, high, n))]
        if n >= 2:
            odd = int(rng.integers(n))
            specs[odd] = (
                ReplicaSpec(speed=config.slow_speed)
                if scenario == "slow"
                else ReplicaSpec(speed=specs[odd].speed, failing=True)
            )
        pools[stage] = specs
    return pools


def _rate_per_s(
    config: SweepConfig, tasks: TaskLengths, pools: dict[str, list[ReplicaSpec]]
) -> float:
    """``load`` times the searches per second the slowest stage can serve."""
    work_s = {kind: ms / 1000.0 for kind, ms in tasks.work_ms().items()}
    capacity = min(
        sum(r.speed for r in specs if not r.failing) / work_s[KIND_OF[stage]]
        for stage, specs in pools.items()
    )
    return config.load * capacity


def run_case(
    config: SweepConfig, tasks: TaskLengths, scenario: str, renderers: int
) -> dict[str, Any]:
    """Every policy on one scenario's replicas and searches at ``renderers`` renderers."""
    rng = np.random.default_rng([config.seed, list(SCENARIOS).index(scenario), renderers])
    sizes = pool_sizes(tasks, renderers)
    pools = replicas(config, scenario, sizes, rng)
    rate = _rate_per_s(config, tasks, pools)
    times = arrivals(rng, config.searches, rate, max(2, renderers), config.burst_share)
    plans = plan_searches(tasks, rng, times)
    results = {}
    for policy in config.policies:
        outcome = simulate(policy, pools, plans, seed=config.seed)
        completed = sorted(outcome.completions.items())
        results[policy] = latency_stats(outcome) | {
            "searches": len(completed),
            "completed_twice": sum(count > 1 for _, count in completed),
            "failed_calls": outcome.failed_calls,
            "timeouts": outcome.timeouts,
        }
    return {"scenario": scenario, **sizes, "rate_per_s": rate, "policies": results}


def goal_met(row: dict[str, Any], policy: str = DEFAULT_POLICY) -> dict[str, Any]:
    """Whether ``policy``'s p99 is at most p2c's and within :data:`GOAL_ORACLE_RATIO` of the
    oracle's, with both ratios."""
    results = row["policies"]
    p99 = results[policy]["p99_ms"]
    vs_p2c, vs_oracle = p99 / results[P2C]["p99_ms"], p99 / results[ORACLE]["p99_ms"]
    return {
        "vs_p2c": vs_p2c,
        "vs_oracle": vs_oracle,
        "met": vs_p2c <= 1.0 + 1e-9 and vs_oracle <= GOAL_ORACLE_RATIO,
    }


def sweep(
    config: SweepConfig, tasks: TaskLengths, progress: Callable[[dict[str, Any]], None]
) -> list[dict[str, Any]]:
    """Every case of ``config``, each handed to ``progress`` as it is done."""
    rows = []
    for scenario in config.scenarios:
        for size in config.sizes:
            row = run_case(config, tasks, scenario, size)
            rows.append(row)
            progress(row)
    return rows
