"""The controller's broker at scale, simulated (issue 24): ``python -m benchmarks.broker_sim``.

A discrete-event simulation (SimPy) of searches flowing through the broker, which chooses each
task's replica with its own code (:mod:`services.controller.placement`), against
power-of-two-choices and an oracle, at 1–256 renderers. Task lengths and search shapes come from
real searches (:mod:`benchmarks.broker_sim.measure`, ``tasks.json``); the model is in
:mod:`benchmarks.broker_sim.model`, the workload in :mod:`benchmarks.broker_sim.workload`, the
sweep in :mod:`benchmarks.broker_sim.sweep`.
"""

from __future__ import annotations

from typing import Final

__all__ = ["ASSUMPTIONS"]

ASSUMPTIONS: Final = (
    "one controller, no admission limit: every search runs as soon as it arrives",
    "a search: the target's detection beside the start view's render, then per iteration render, "
    "detect, optimize (an iteration at a pose seen before only optimizes); its (renders, "
    "iterations) drawn from real reprojection searches on built-in and generated scenes",
    "task lengths drawn independently from the per-kind percentiles of the stage timings real "
    "searches recorded (HTTP included, one search at a time), divided by the replica's speed",
    "a replica serves one task at a time, first come first served; speeds log-uniform in "
    "×0.5–×2; detectors and optimizers in proportion to the work a search asks of them",
    "arrivals at 0.7 of the slowest stage's capacity: a quarter of the searches in bursts (as "
    "many at one instant as there are renderers), the rest uniform over the same span",
    "the broker's defaults: 4 attempts, 50 ms backoff doubling, out after 3 failures in a row "
    "for 5 s, /health every 2 s (every replica answers, with its queue), the stage timeouts",
    "p50/p99: search latency from arrival to the optimizer's last answer; searches/s: searches "
    "over the span from the first arrival to the last answer; every policy serves the same "
    "searches on the same replicas",
)
