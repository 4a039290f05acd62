"""The bench's statistics: per-(scene, strategy, variant) summaries of its searches and paper
eq. 9 measured against the step-by-step strategy.

Definitions used in every table
-------------------------------
success
    The search succeeded and its grid pose is the grid pose nearest the true pose, confirmed or
    not; the success column says how many of those answers were unconfirmed (``confirmed:
    false``, the best visited pose after no view matched).
renders
    Distinct views rendered by the search, the start view included (``result.renders``).
steps (moves)
    Views visited after the start view: iterations − 1. The paper's "steps".
wall
    From sending ``POST /searches`` to receiving the search's ``end`` event.
render / detect / optimize
    Sums over a search's iterations of the controller's stage timings (``timings.*_ms``).
HTTP+queue
    Wall time minus those three sums: the submission, queueing, the target's detection where it
    did not overlap the start render, storing iterations, the events stream.
Percentiles are the sample's own values (inverted CDF), never interpolated between searches.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from cosmos.bench.runner import SearchRecord
from cosmos.bench.variants import VARIANTS

__all__ = [
    "PAPER_EQ9",
    "PAPER_OPTIMISED_STEPS",
    "PAPER_SIMPLE_STEPS",
    "STRATEGY_ORDER",
    "Eq9Row",
    "Summary",
    "eq9_rows",
    "percentile",
    "rank",
    "ranked",
    "strategy_label",
    "summarize",
]

PAPER_SIMPLE_STEPS: Final = 36
PAPER_OPTIMISED_STEPS: Final = 2
PAPER_EQ9: Final = (PAPER_OPTIMISED_STEPS - PAPER_SIMPLE_STEPS) / PAPER_SIMPLE_STEPS
STRATEGY_ORDER: Final = ("simple", "paper", "reprojection")


def strategy_label(record: SearchRecord) -> str:
    """A search's strategy, and how it started when not given its start: ``reprojection`` (the
    bench's random start, given), ``reprojection, predicted start``."""
    return record.strategy if record.start_given else f"{record.strategy}, predicted start"


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile of ``values`` as one of its own values (NaN when empty)."""
    if not values:
        return math.nan
    return float(np.percentile(np.asarray(values, dtype=np.float64), q, method="inverted_cdf"))


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def rank(value: str, order: Sequence[str]) -> int:
    """``value``'s place in ``order``; a value not in it comes after every one that is."""
    return order.index(value) if value in order else len(order)


def ranked(values: Iterable[str], order: Sequence[str]) -> list[str]:
    """The distinct ``values`` in ``order``, those not in it after them by name."""
    return sorted(set(values), key=lambda v: (rank(v, order), v))


@dataclass(frozen=True)
class Summary:
    """One (scene, strategy, variant) cell of the bench; ``strategy`` is
    :func:`strategy_label`'s."""

    scene: str
    strategy: str
    variant: str
    n: int
    succeeded: int
    errors: int
    unconfirmed_succeeded: int
    renders_mean: float
    renders_p50: float
    renders_p95: float
    renders_max: float
    moves_mean: float
    moves_max: float
    wall_p50_ms: float
    wall_p95_ms: float
    render_ms: float
    detect_ms: float
    optimize_ms: float
    other_ms: float
    refined_p50_deg: float
    refined_p95_deg: float

    @property
    def success_rate(self) -> float:
        return self.succeeded / self.n if self.n else math.nan


def summarize(records: Iterable[SearchRecord]) -> list[Summary]:
    """One summary per (scene, strategy, variant), ordered by variant, scene, strategy."""
    groups: dict[tuple[str, str, str], list[SearchRecord]] = {}
    for record in records:
        key = (record.scene, strategy_label(record), record.variant)
        groups.setdefault(key, []).append(record)
    out = []
    for (scene, strategy, variant), group in groups.items():
        ran = [r for r in group if r.status != "error"]
        renders = [float(r.renders) for r in ran]
        moves = [float(r.moves) for r in ran]
        walls = [r.wall_ms for r in ran]
        refined = [r.refined_error_deg for r in ran if r.refined_error_deg is not None]
        out.append(
            Summary(
                scene=scene,
                strategy=strategy,
                variant=variant,
                n=len(group),
                succeeded=sum(r.success for r in group),
                errors=len(group) - len(ran),
                unconfirmed_succeeded=sum(r.success and r.confirmed is False for r in group),
                renders_mean=_mean(renders),
                renders_p50=percentile(renders, 50),
                renders_p95=percentile(renders, 95),
                renders_max=max(renders, default=math.nan),
                moves_mean=_mean(moves),
                moves_max=max(moves, default=math.nan),
                wall_p50_ms=percentile(walls, 50),
                wall_p95_ms=percentile(walls, 95),
                render_ms=_mean([r.render_ms for r in ran]),
                detect_ms=_mean([r.detect_ms for r in ran]),
                optimize_ms=_mean([r.optimize_ms for r in ran]),
                other_ms=_mean([r.other_ms for r in ran]),
                refined_p50_deg=percentile(refined, 50),
                refined_p95_deg=percentile(refined, 95),
            )
        )
    variant_rank: dict[str, int] = {v: i for i, v in enumerate(VARIANTS)}
    out.sort(
        key=lambda s: (
            variant_rank.get(s.variant, 99),
            s.scene,
            rank(s.strategy.split(",")[0], STRATEGY_ORDER),
            s.strategy,
        )
    )
    return out


@dataclass(frozen=True)
class Eq9Row:
    """Paper eq. 9 measured for one strategy against ``simple`` on one (scene, variant).

    .. math:: \\text{improvement} = \\frac{s_o − s_s}{s_s}

    with s_o the strategy's steps and s_s the step-by-step strategy's, both counted as moves
    after the start view (their means, or their worst cases); NaN where s_s = 0. The paper's
    figure, :data:`PAPER_EQ9` = (2 − 36) / 36 ≈ −94.44 %, compares a worst case of 36 steps.
    The same ratio of mean renders is the change in views rendered.
    """

    scene: str
    variant: str
    strategy: str
    moves_mean: float
    simple_moves_mean: float
    moves_max: float
    simple_moves_max: float
    renders_mean: float
    simple_renders_mean: float

    @staticmethod
    def _change(new: float, old: float) -> float:
        return (new - old) / old if old else math.nan

    @property
    def mean_change(self) -> float:
        return self._change(self.moves_mean, self.simple_moves_mean)

    @property
    def worst_change(self) -> float:
        return self._change(self.moves_max, self.simple_moves_max)

    @property
    def renders_change(self) -> float:
        return self._change(self.renders_mean, self.simple_renders_mean)


def eq9_rows(summaries: Sequence[Summary]) -> list[Eq9Row]:
    """paper and reprojection against simple, per scene and variant (where simple ran)."""
    by = {(s.scene, s.variant, s.strategy): s for s in summaries}
    rows = []
    for s in summaries:
        simple = by.get((s.scene, s.variant, "simple"))
        if s.strategy == "simple" or simple is None:
            continue
        rows.append(
            Eq9Row(
                scene=s.scene,
                variant=s.variant,
                strategy=s.strategy,
                moves_mean=s.moves_mean,
                simple_moves_mean=simple.moves_mean,
                moves_max=s.moves_max,
                simple_moves_max=simple.moves_max,
                renders_mean=s.renders_mean,
                simple_renders_mean=simple.renders_mean,
            )
        )
    return rows
