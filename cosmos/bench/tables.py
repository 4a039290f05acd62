"""The bench's tables, as plain text for a terminal and as Markdown: one row per
(scene, strategy) for each target variant, then paper eq. 9 against the step-by-step strategy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final

from cosmos.bench.stats import (
    PAPER_EQ9,
    PAPER_OPTIMISED_STEPS,
    PAPER_SIMPLE_STEPS,
    Eq9Row,
    Summary,
    eq9_rows,
)

__all__ = [
    "EQ9_NOTE",
    "SUMMARY_COLUMNS",
    "markdown_tables",
    "md_table",
    "plain_table",
    "summary_cells",
    "text_tables",
]


def plain_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Columns padded to their widest cell, two spaces apart."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(lines)


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown (GFM) table; cells are written as they are."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


SUMMARY_COLUMNS: Final = (
    "scene",
    "strategy",
    "n",
    "success",
    "renders mean/p50/p95/max",
    "steps mean/max",
    "wall p50/p95 ms",
    "render ms",
    "detect ms",
    "optimize ms",
    "HTTP+queue ms",
    "refined err p50/p95 °",
)


def _f(value: float, digits: int = 0) -> str:
    return "—" if not math.isfinite(value) else f"{value:.{digits}f}"


def summary_cells(s: Summary) -> list[str]:
    """One summary's row under :data:`SUMMARY_COLUMNS` (— where a figure has no searches)."""
    errors = f" ({s.errors} errors)" if s.errors else ""
    unconfirmed = f" ({s.unconfirmed_succeeded} unconfirmed)" if s.unconfirmed_succeeded else ""
    return [
        s.scene,
        s.strategy,
        str(s.n),
        f"{100 * s.success_rate:.1f}%{unconfirmed}{errors}",
        f"{_f(s.renders_mean, 2)} / {_f(s.renders_p50)} / {_f(s.renders_p95)} / "
        f"{_f(s.renders_max)}",
        f"{_f(s.moves_mean, 2)} / {_f(s.moves_max)}",
        f"{_f(s.wall_p50_ms)} / {_f(s.wall_p95_ms)}",
        _f(s.render_ms),
        _f(s.detect_ms),
        _f(s.optimize_ms),
        _f(s.other_ms),
        f"{_f(s.refined_p50_deg, 2)} / {_f(s.refined_p95_deg, 2)}",
    ]


_VARIANT_TITLES: Final = {
    "clean": "on-grid, clean",
    "jpeg": "on-grid, JPEG quality 60",
    "noise": "on-grid, Gaussian pixel noise σ = 6",
    "offgrid": "off-grid (θ, φ up to ⅓ step from a grid pose)",
    "photo": "on-grid, a photo (light moved, exposure, gamma, blur)",
    "changed": "on-grid, the scene changed (an object moved or left out)",
}


def _eq9_cells(row: Eq9Row) -> list[str]:
    return [
        row.scene,
        row.variant,
        row.strategy,
        f"{row.moves_mean:.2f} vs {row.simple_moves_mean:.2f}",
        f"{row.mean_change:+.2%}",
        f"{row.moves_max:.0f} vs {row.simple_moves_max:.0f}",
        f"{row.worst_change:+.2%}",
        f"{row.renders_mean:.2f} vs {row.simple_renders_mean:.2f}",
        f"{row.renders_change:+.2%}",
    ]


_EQ9_COLUMNS: Final = (
    "scene",
    "variant",
    "strategy",
    "mean steps vs simple",
    "eq. 9 (mean)",
    "worst steps vs simple",
    "eq. 9 (worst)",
    "mean renders vs simple",
    "change in renders",
)

EQ9_NOTE: Final = (
    f"paper eq. 9 at angle_step = π/24: ({PAPER_OPTIMISED_STEPS} − {PAPER_SIMPLE_STEPS}) / "
    f"{PAPER_SIMPLE_STEPS} = {PAPER_EQ9:+.2%} (steps = moves after the start view = "
    "iterations − 1; the paper's 36 is the step-by-step worst case)"
)


def _by_variant(summaries: Sequence[Summary]) -> dict[str, list[Summary]]:
    out: dict[str, list[Summary]] = {}
    for s in summaries:
        out.setdefault(s.variant, []).append(s)
    return out


def text_tables(summaries: Sequence[Summary]) -> str:
    """The bench's tables for a terminal: one per variant, then eq. 9."""
    parts = []
    for variant, group in _by_variant(summaries).items():
        parts.append(f"targets: {_VARIANT_TITLES.get(variant, variant)}")
        parts.append(plain_table(SUMMARY_COLUMNS, [summary_cells(s) for s in group]))
        parts.append("")
    eq9 = eq9_rows(summaries)
    if eq9:
        parts.append(EQ9_NOTE)
        parts.append(plain_table(_EQ9_COLUMNS, [_eq9_cells(r) for r in eq9]))
    return "\n".join(parts)


def markdown_tables(summaries: Sequence[Summary]) -> str:
    """The same tables in Markdown."""
    parts = []
    for variant, group in _by_variant(summaries).items():
        parts.append(f"#### Targets {_VARIANT_TITLES.get(variant, variant)}\n")
        parts.append(md_table(SUMMARY_COLUMNS, [summary_cells(s) for s in group]) + "\n")
    eq9 = eq9_rows(summaries)
    if eq9:
        parts.append("#### Paper eq. 9\n")
        parts.append(EQ9_NOTE + ".\n")
        parts.append(md_table(_EQ9_COLUMNS, [_eq9_cells(r) for r in eq9]) + "\n")
    return "\n".join(parts)
