"""The random-scene bench's figures: success per θ band × target variant × detector arm, the
goals and the failures' traces (its section of ``docs/RESULTS.md`` is :mod:`.results_md`).

Definitions
-----------
found
    The search answered the true grid pose (the pose nearest the target's), confirmed or not.
confirmed
    Found, the search succeeded and the controller confirmed the answer (``result.confirmed``;
    a controller that does not report it confirmed every answer).
unconfirmed
    Searches answering with ``confirmed: false`` (an any-time best-visited pose), and how many of
    those answers were the true pose.
confirmed wrong
    Searches that confirmed a grid pose other than the true one: worse than a miss, since a
    user is told it was found.
θ band
    Of the target's true pose: θ < 30°, 30° ≤ θ ≤ 60°, θ > 60°.
arm
    ``general``: the shipped detector; ``scene``: the scene's own, after onboarding; ``…,
    predicted start``: searched without a start, which the controller predicted from the
    target (the others are given the bench's random start, the paper's protocol).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

from cosmos.bench.runner import SearchRecord
from cosmos.bench.stats import percentile, ranked
from cosmos.bench.tables import md_table, plain_table
from cosmos.bench.variants import SCENE_VARIANTS, VARIANTS

__all__ = [
    "ALL",
    "BANDS",
    "FAILURE_HEADER",
    "GOALS",
    "BandCell",
    "arm_label",
    "band_cells",
    "band_table",
    "failure_rows",
    "goal_checks",
    "theta_band",
]

BANDS: Final = ("θ < 30°", "30–60°", "θ > 60°")
ALL: Final = "all"
ARM_ORDER: Final = ("general", "scene")
GOAL_OVERALL: Final = 0.99
GOAL_CELL: Final = 0.98
GOAL_ALTERED: Final = 0.95
GOAL_RENDERS_P50: Final = 2.0
GOAL_PREDICTED_RENDERS_P50: Final = 1.0
PREDICTED: Final = "predicted start"
GOALS: Final = (
    f"found ≥ {GOAL_OVERALL:.0%} overall, ≥ {GOAL_CELL:.0%} in every θ band and every variant "
    f"(photo and changed ≥ {GOAL_ALTERED:.0%}), median renders ≤ {GOAL_RENDERS_P50:.0f} "
    f"(≤ {GOAL_PREDICTED_RENDERS_P50:.0f} with a {PREDICTED}); per arm"
)


def theta_band(theta_deg: float) -> str:
    """The θ band of a true pose (module docstring)."""
    if theta_deg < 30.0:
        return BANDS[0]
    return BANDS[1] if theta_deg <= 60.0 else BANDS[2]


@dataclass(frozen=True)
class BandCell:
    """The searches of one (arm, variant, band); ``variant`` or ``band`` may be :data:`ALL`."""

    arm: str
    variant: str
    band: str
    n: int
    found: int
    confirmed: int
    unconfirmed: int
    unconfirmed_found: int
    confirmed_wrong: int
    errors: int
    renders_p50: float
    renders_p95: float

    @property
    def found_rate(self) -> float:
        return self.found / self.n if self.n else math.nan

    @property
    def confirmed_rate(self) -> float:
        return self.confirmed / self.n if self.n else math.nan


def _cell(arm: str, variant: str, band: str, records: Sequence[SearchRecord]) -> BandCell:
    ran = [r for r in records if r.status != "error"]
    renders = [float(r.renders) for r in ran]
    unconfirmed = [r for r in records if r.confirmed is False]
    return BandCell(
        arm=arm,
        variant=variant,
        band=band,
        n=len(records),
        found=sum(r.found_truth for r in records),
        confirmed=sum(r.success and r.confirmed is not False for r in records),
        unconfirmed=len(unconfirmed),
        unconfirmed_found=sum(r.found_truth for r in unconfirmed),
        confirmed_wrong=sum(
            r.status == "succeeded" and not r.found_truth and r.confirmed is not False
            for r in records
        ),
        errors=len(records) - len(ran),
        renders_p50=percentile(renders, 50),
        renders_p95=percentile(renders, 95),
    )


def arm_label(record: SearchRecord) -> str:
    """A search's detector arm, and how it started when not given its start (``general``,
    ``general, predicted start``)."""
    return record.arm if record.start_given else f"{record.arm}, {PREDICTED}"


def band_cells(
    records: Sequence[SearchRecord], label: Callable[[SearchRecord], str] = arm_label
) -> list[BandCell]:
    """Every (arm, variant, band) cell with searches, plus each arm's and variant's totals
    (``band`` = all) and each arm's band totals (``variant`` = all); the "arm" is ``label``'s
    (:func:`arm_label`; the main bench's strategy and start, for one)."""
    cells = []
    for arm in ranked((label(r) for r in records), ARM_ORDER):
        mine = [r for r in records if label(r) == arm]
        for variant in [*ranked((r.variant for r in mine), VARIANTS), ALL]:
            group = [r for r in mine if variant in (ALL, r.variant)]
            for band in (*BANDS, ALL):
                subset = [r for r in group if band in (ALL, theta_band(r.true_theta_deg))]
                if subset:
                    cells.append(_cell(arm, variant, band, subset))
    return cells


def _rate(cell: BandCell | None) -> str:
    if cell is None:
        return "—"
    return f"{cell.found}/{cell.n} = {100 * cell.found_rate:.1f}%"


_HEADER: Final = (
    "variant",
    *BANDS,
    "all",
    "confirmed (all)",
    "unconfirmed (at truth)",
    "confirmed wrong",
    "renders p50 / p95",
)


def _rows(cells: Sequence[BandCell]) -> list[list[str]]:
    by = {(c.arm, c.variant, c.band): c for c in cells}
    rows = []
    for arm, variant in dict.fromkeys((c.arm, c.variant) for c in cells):
        total = by[(arm, variant, ALL)]
        errors = f" ({total.errors} errors)" if total.errors else ""
        rows.append(
            [
                arm,
                variant,
                *(_rate(by.get((arm, variant, band))) for band in BANDS),
                _rate(total) + errors,
                f"{total.confirmed}/{total.n} = {100 * total.confirmed_rate:.1f}%",
                f"{total.unconfirmed} ({total.unconfirmed_found})",
                str(total.confirmed_wrong),
                f"{total.renders_p50:.0f} / {total.renders_p95:.0f}",
            ]
        )
    return rows


def band_table(cells: Sequence[BandCell], *, markdown: bool = False, title: str = "arm") -> str:
    """The θ band × variant × arm table (found = k/n, then confirmed, unconfirmed, renders);
    ``title`` heads the arm's column."""
    return (md_table if markdown else plain_table)((title, *_HEADER), _rows(cells))


def goal_checks(cells: Sequence[BandCell]) -> list[str]:
    """One line per arm and goal: met or missed, with the figure."""
    lines = []
    for arm in dict.fromkeys(c.arm for c in cells):
        mine = [c for c in cells if c.arm == arm]
        overall = next(c for c in mine if c.variant == ALL and c.band == ALL)

        def verdict(ok: bool) -> str:
            return "met" if ok else "MISSED"

        lines.append(
            f"{arm}: overall {100 * overall.found_rate:.1f}% (goal ≥ {GOAL_OVERALL:.0%}): "
            f"{verdict(overall.found_rate >= GOAL_OVERALL)}"
        )
        low = []
        for c in mine:
            if (c.variant == ALL) == (c.band == ALL):
                continue  # only the per-band and per-variant totals are goals
            goal = GOAL_ALTERED if c.variant in SCENE_VARIANTS else GOAL_CELL
            if c.found_rate < goal:
                low.append(f"{c.variant}/{c.band} {100 * c.found_rate:.1f}% (< {goal:.0%})")
        lines.append(
            f"{arm}: every band and variant at goal: "
            + (verdict(True) if not low else "MISSED: " + ", ".join(low))
        )
        renders_goal = GOAL_PREDICTED_RENDERS_P50 if arm.endswith(PREDICTED) else GOAL_RENDERS_P50
        lines.append(
            f"{arm}: median renders {overall.renders_p50:.0f} (goal ≤ {renders_goal:.0f}): "
            f"{verdict(overall.renders_p50 <= renders_goal)}"
        )
    return lines


def _match_text(match: Any) -> str:
    """The optimizer's match of a view (``ViewMatch`` JSON), briefly; empty when not given."""
    if not isinstance(match, Mapping) or "score" not in match:
        return ""
    rms = match.get("rms_px")
    boxes = f"RMS {rms:.2f} px" if isinstance(rms, int | float) else "no pairs"
    return (
        f" (match score {match['score']:.2f}: {boxes}, noise {match.get('noise_px', 0):.2f} px, "
        f"{match.get('pairs', 0)} pairs)"
    )


def failure_rows(records: Sequence[SearchRecord], limit: int = 40) -> list[list[str]]:
    """The traced searches (misses and unconfirmed answers), up to ``limit``."""
    rows = []
    for r in records:
        t = r.trace
        if t is None:
            continue
        visited = (
            f"yes, at {t.visit_iteration}{_match_text(t.visit_match)}: {t.visit_reason or '—'}"
            if t.truth_visited
            else "no"
        )
        dets = (
            f"{t.visit_detections} vs {t.target_detections}"
            if t.visit_detections is not None
            else f"— vs {t.target_detections}"
        )
        found = f"({r.found.lat}, {r.found.lon})" if r.found is not None else "—"
        rows.append(
            [
                r.scene,
                r.arm,
                r.variant,
                f"{r.true_theta_deg:.1f}",
                f"({r.truth.lat}, {r.truth.lon})",
                found + ("" if r.confirmed is not False else " unconfirmed"),
                visited,
                dets,
                f"{t.status}: {t.final_reason}",
                r.change or "—",
            ]
        )
        if len(rows) == limit:
            break
    return rows


FAILURE_HEADER: Final = (
    "scene",
    "arm",
    "variant",
    "true θ°",
    "truth",
    "answer",
    "truth visited (iteration: optimizer's reason)",
    "detections there vs target",
    "end",
    "scene change",
)
