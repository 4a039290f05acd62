"""The simulated searches: task lengths drawn from the measured ones, arrivals with bursts.

A search is the controller's loop (:mod:`services.controller.loop`): it detects its target while
it renders its start view, then per iteration renders the view, detects its objects and asks the
optimizer for the next pose; an iteration at a pose seen before only asks the optimizer. Its
(renders, iterations) is drawn from the real searches' (``tasks.json``); every task's length
independently from its kind's measured percentiles (inverse CDF, linear between percentiles),
a target's detection from the detections'.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.broker_sim.measure import TASKS_JSON

__all__ = ["SearchPlan", "TaskLengths", "arrivals", "plan_searches", "pool_sizes"]


@dataclass(frozen=True)
class SearchPlan:
    """One search's arrival (s) and the lengths (ms, on a replica of speed 1) of its tasks."""

    number: int
    arrival_s: float
    target_ms: float
    render_ms: tuple[float, ...]
    detect_ms: tuple[float, ...]
    optimize_ms: tuple[float, ...]


@dataclass(frozen=True)
class TaskLengths:
    """The measured task lengths (percentiles per kind) and search shapes."""

    percentiles: Mapping[str, Sequence[float]]
    shapes: Sequence[tuple[int, int]]
    """(renders, iterations) of each distinct shape."""
    weights: Sequence[float]
    """The share of the measured searches with each shape."""
    source: Mapping[str, Any]

    @classmethod
    def load(cls, path: Path = TASKS_JSON) -> TaskLengths:
        data = json.loads(path.read_text())
        shapes = [(int(s["renders"]), int(s["iterations"])) for s in data["shapes"]]
        counts = np.array([s["searches"] for s in data["shapes"]], dtype=float)
        return cls(
            percentiles=data["task_ms_percentiles"],
            shapes=shapes,
            weights=tuple(float(w) for w in counts / counts.sum()),
            source=data,
        )

    def draw(self, kind: str, rng: np.random.Generator, n: int) -> tuple[float, ...]:
        """``n`` lengths (ms) of ``kind`` tasks: the inverse CDF of the percentiles at U(0, 1)."""
        levels = np.arange(len(self.percentiles[kind]), dtype=float)
        values = np.interp(rng.uniform(0.0, levels[-1], n), levels, self.percentiles[kind])
        return tuple(float(v) for v in values)

    def mean_ms(self, kind: str) -> float:
        """The mean length of a ``kind`` task (trapezoid over the percentiles)."""
        q = np.asarray(self.percentiles[kind], dtype=float)
        return float((q[:-1] + q[1:]).sum() / 2.0 / (len(q) - 1))

    def mean_tasks(self) -> dict[str, float]:
        """Tasks of each kind in a mean search (a target's detection included)."""
        renders = sum(w * r for w, (r, _) in zip(self.weights, self.shapes, strict=True))
        iterations = sum(w * i for w, (_, i) in zip(self.weights, self.shapes, strict=True))
        return {"render": renders, "detect": renders + 1.0, "optimize": iterations}

    def work_ms(self) -> dict[str, float]:
        """The mean work (ms) a search asks of each kind of replica."""
        return {kind: n * self.mean_ms(kind) for kind, n in self.mean_tasks().items()}


def arrivals(
    rng: np.random.Generator, n: int, rate_per_s: float, burst_size: int, burst_share: float
) -> list[float]:
    """``n`` arrival times (s) at ``rate_per_s`` on average: about ``burst_share`` of them in
    bursts of ``burst_size`` searches at one instant, the others a Poisson process (uniform
    times over the same span), each burst at a uniform time in it."""
    span = n / rate_per_s
    bursts = min(n // burst_size, round(burst_share * n / burst_size)) if burst_size > 1 else 0
    steady = n - bursts * burst_size
    times = list(rng.uniform(0.0, span, steady))
    for at in rng.uniform(0.0, span, bursts):
        times.extend([float(at)] * burst_size)
    return sorted(float(t) for t in times)


def plan_searches(
    tasks: TaskLengths, rng: np.random.Generator, arrival_s: Sequence[float]
) -> list[SearchPlan]:
    """A search for each arrival time, its shape and task lengths drawn from ``tasks``."""
    picks = rng.choice(len(tasks.shapes), size=len(arrival_s), p=np.asarray(tasks.weights))
    plans = []
    for number, (at, pick) in enumerate(zip(arrival_s, picks, strict=True)):
        renders, iterations = tasks.shapes[int(pick)]
        plans.append(
            SearchPlan(
                number=number,
                arrival_s=at,
                target_ms=tasks.draw("detect", rng, 1)[0],
                render_ms=tasks.draw("render", rng, renders),
                detect_ms=tasks.draw("detect", rng, renders),
                optimize_ms=tasks.draw("optimize", rng, max(iterations, renders)),
            )
        )
    return plans


def pool_sizes(tasks: TaskLengths, renderers: int) -> dict[str, int]:
    """Replicas per stage: ``renderers``, and detectors and optimizers in proportion to the
    work a search asks of them (rounded up), so every stage is about as busy."""
    work = tasks.work_ms()
    return {
        "renderer": renderers,
        "detector": max(1, math.ceil(renderers * work["detect"] / work["render"])),
        "optimizer": max(1, math.ceil(renderers * work["optimize"] / work["render"])),
    }
