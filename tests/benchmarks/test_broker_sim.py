"""The broker simulation at a tiny size: its invariants, its determinism, its measured input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.broker_sim.__main__ import main
from benchmarks.broker_sim.model import (
    ORACLE,
    POLICIES,
    ReplicaSpec,
    latency_stats,
    simulate,
)
from benchmarks.broker_sim.sweep import SweepConfig, run_case
from benchmarks.broker_sim.workload import TaskLengths, arrivals, plan_searches
from cosmos.bench.results_md import section_of_broker_sim

TINY = SweepConfig(sizes=(4,), searches=150)


@pytest.fixture(scope="module")
def tasks() -> TaskLengths:
    return TaskLengths.load()


@pytest.fixture(scope="module", params=["slow", "failing"])
def case(request, tasks):
    return run_case(TINY, tasks, request.param, 4)


def test_every_search_completes_exactly_once_under_every_policy(case):
    for policy, result in case["policies"].items():
        assert (result["searches"], result["completed_twice"]) == (TINY.searches, 0), policy


def test_the_oracle_is_never_worse_on_mean_latency(case):
    oracle = case["policies"][ORACLE]["mean_ms"]
    for policy, result in case["policies"].items():
        assert oracle <= result["mean_ms"] * (1 + 1e-9), policy
    assert case["policies"][ORACLE]["failed_calls"] == 0  # it knows which replica fails


def test_a_failing_replica_makes_the_others_retry(tasks):
    failing = run_case(TINY, tasks, "failing", 4)["policies"]
    assert all(failing[p]["failed_calls"] > 0 for p in POLICIES if p != ORACLE)


def test_runs_are_deterministic(tasks, case):
    again = run_case(TINY, tasks, case["scenario"], 4)
    assert json.dumps(again, sort_keys=True) == json.dumps(case, sort_keys=True)


def test_an_idle_replica_serves_a_search_in_the_sum_of_its_task_lengths(tasks):
    rng = np.random.default_rng(0)
    (plan,) = plan_searches(tasks, rng, [0.0])
    pools = {stage: [ReplicaSpec(speed=2.0)] for stage in ("renderer", "detector", "optimizer")}
    # the target's detection runs beside the first render, the view's detection after both
    first = max(plan.render_ms[0], plan.target_ms) + plan.detect_ms[0]
    serial_ms = (
        first + sum(plan.render_ms[1:]) + sum(plan.detect_ms[1:]) + sum(plan.optimize_ms)
    ) / 2.0
    for policy in POLICIES:
        outcome = simulate(policy, pools, [plan])
        assert latency_stats(outcome)["p50_ms"] == pytest.approx(serial_ms), policy


def test_bursts_and_rate(tasks):
    rng = np.random.default_rng(1)
    times = arrivals(rng, 1000, rate_per_s=50.0, burst_size=10, burst_share=0.25)
    assert len(times) == 1000
    assert times == sorted(times)
    assert max(times) == pytest.approx(20.0, rel=0.05)
    assert sum(np.diff(times) == 0) == 25 * 9  # 25 bursts of 10 searches at one instant


def test_the_stored_task_lengths_come_from_real_searches(tasks):
    for kind, percentiles in tasks.percentiles.items():
        assert len(percentiles) == 101, kind
        assert np.all(np.diff(percentiles) >= 0), kind
    assert tasks.mean_ms("render") > tasks.mean_ms("detect") > 0
    median_renders = tasks.shapes[int(np.searchsorted(np.cumsum(tasks.weights), 0.5))][0]
    assert median_renders == 2  # the default strategy's searches
    assert set(tasks.source["sources"][0]) >= {"report", "command", "commit", "searches"}


def test_the_command_writes_its_report(tmp_path, capsys):
    out = tmp_path / "broker_sim.json"
    assert main(["--sizes", "2", "--searches", "40", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert [row["renderer"] for row in report["rows"]] == [2, 2]
    assert "p99÷oracle" in capsys.readouterr().out


def test_results_md_holds_the_committed_report():
    root = Path(__file__).resolve().parents[2]
    report = json.loads((root / "docs/results/broker_sim.json").read_text())
    assert section_of_broker_sim(report) in (root / "docs/RESULTS.md").read_text()
    assert all(row["goal"]["met"] for row in report["rows"])  # else the default must change
