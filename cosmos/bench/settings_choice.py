"""The render setting the sweep chooses from its searches through the stack (``--sweep``).

Each run searched at one (film width, spp); a run's figures are its success rate, its mean
renders per search r and its median search wall time. The reference is the most expensive run:
the largest film (the scene's own, when no width was set), then the most spp. A run s is good
when it loses nothing against the reference ref:

* as many successes in all: Σ_c k_c(s) ≥ Σ_c k_c(ref), with k_c successes in the
  (scene, variant) cell c;
* no cell more than one search down: k_c(s) ≥ k_c(ref) − 1 for every cell of ref;
* renders within 5 % + 0.05: r(s) ≤ 1.05 r(ref) + 0.05.

The choice is the good run with the least median wall time (the reference is always good).
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from cosmos.bench.runner import SearchRecord

__all__ = ["CHOICE_RULE", "choose_setting"]


@dataclass(frozen=True)
class _Setting:
    """One sweep run's outcome: the film and spp, successes per (scene, variant), costs."""

    width: int | None
    spp: int
    cells: Mapping[tuple[str, str], int]
    success: float
    renders: float
    wall_ms: float

    @property
    def name(self) -> str:
        return f"{self.width or 'scene'} px wide at {self.spp} spp"


CHOICE_RULE: Final = (
    "the cheapest setting by median search wall time whose searches lose nothing against the "
    "largest film at the most spp: as many successes in all, no (scene, variant) cell more than "
    "one search down, renders per search within 5 % + 0.05"
)


def choose_setting(searches: Sequence[Mapping[str, Any]]) -> str:
    """The setting the rule (module docstring) picks from the sweep's search runs (``width``,
    ``spp``, ``records`` each), against the reference's figures; empty when no run has records."""
    settings = []
    for run in searches:
        records = [SearchRecord.model_validate(r) for r in run["records"]]
        if not records:
            continue
        cells: dict[tuple[str, str], int] = {}
        for r in records:
            cells[(r.scene, r.variant)] = cells.get((r.scene, r.variant), 0) + int(r.success)
        settings.append(
            _Setting(
                width=run["width"],
                spp=run["spp"],
                cells=cells,
                success=float(np.mean([r.success for r in records])),
                renders=float(np.mean([r.renders for r in records])),
                wall_ms=statistics.median(r.wall_ms for r in records),
            )
        )
    if not settings:
        return ""
    ref = max(settings, key=lambda s: (s.width or 1 << 30, s.spp))
    good = [
        s
        for s in settings
        if sum(s.cells.values()) >= sum(ref.cells.values())
        and all(s.cells.get(k, 0) >= n - 1 for k, n in ref.cells.items())
        and s.renders <= ref.renders * 1.05 + 0.05
    ]
    best = min(good, key=lambda s: s.wall_ms)
    return (
        f"{best.name}: success {best.success:.1%} and {best.renders:.2f} renders per search, "
        f"median wall {best.wall_ms:.0f} ms, against {ref.success:.1%}, {ref.renders:.2f} and "
        f"{ref.wall_ms:.0f} ms at {ref.name}"
    )
