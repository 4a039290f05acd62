"""The bench's plots (matplotlib, Agg) and ``docs/RESULTS.md``; the statistics are
:mod:`.stats`, the tables :mod:`.tables`, the machine :mod:`.machine`.
"""

from __future__ import annotations

import io
import json
import os
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from services.bench.runner import SearchRecord
from services.bench.stats import STRATEGY_ORDER, ranked, summarize
from services.bench.tables import SUMMARY_COLUMNS, markdown_tables, md_table, summary_cells
from services.bench.variants import VARIANTS

__all__ = [
    "choose_setting",
    "section_head",
    "write_plots",
    "write_results_md",
]

# -- plots ----------------------------------------------------------------------------------


def write_plots(records: Sequence[SearchRecord], out: Path) -> list[Path]:
    """``renders_hist.png`` (renders per search, per strategy and variant) and
    ``distance.png`` (angle from the camera to the true pose per iteration, clean on-grid
    targets, like the paper's Fig. 8). Returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    strategies = ranked((r.strategy for r in records), STRATEGY_ORDER)
    written: list[Path] = []
    if not strategies:
        return written

    fig, axes = plt.subplots(
        1, len(strategies), figsize=(4.2 * len(strategies), 3.4), squeeze=False
    )
    for ax, strategy in zip(axes[0], strategies, strict=True):
        mine = [r for r in records if r.strategy == strategy and r.status != "error"]
        top = max((r.renders for r in mine), default=1)
        bins = np.arange(0.5, top + 1.5, 1.0)
        for variant in VARIANTS:
            values = [r.renders for r in mine if r.variant == variant]
            if values:
                ax.hist(values, bins=bins, histtype="step", linewidth=1.5, label=variant)
        ax.set_title(strategy)
        ax.set_xlabel("renders per search (start view included)")
        ax.set_ylabel("searches")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "renders_hist.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    fig, axes = plt.subplots(
        1, len(strategies), figsize=(4.2 * len(strategies), 3.4), squeeze=False, sharey=True
    )
    for ax, strategy in zip(axes[0], strategies, strict=True):
        mine = [r for r in records if r.strategy == strategy and r.variant == "clean"]
        curves = [[t.distance_deg for t in r.trajectory] for r in mine if r.trajectory]
        for curve in curves:
            ax.plot(range(1, len(curve) + 1), curve, color="0.6", linewidth=0.6, alpha=0.5)
        if curves:
            length = max(len(c) for c in curves)
            # A finished search stays where it ended: pad each curve with its last distance.
            padded = np.array([c + [c[-1]] * (length - len(c)) for c in curves])
            ax.plot(
                range(1, length + 1),
                np.median(padded, axis=0),
                color="C3",
                linewidth=2.0,
                label="median",
            )
            ax.legend(fontsize=8)
        ax.set_title(f"{strategy} (clean targets)")
        ax.set_xlabel("iteration (1 = start view)")
        ax.set_ylabel("angle to the true pose (°)")
    fig.tight_layout()
    path = out / "distance.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


# -- render settings -----------------------------------------------------------------------


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
    """The cheapest render setting (median search wall time) whose searches lose nothing against
    the reference, the most expensive setting (largest film, then most spp): as many searches
    succeed in all, no (scene, variant) cell has more than one fewer, and renders per search stay
    within 5 % + 0.05 of the reference's."""
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


# -- RESULTS.md -----------------------------------------------------------------------------


def _machine_md(machine: Mapping[str, Any]) -> str:
    return "\n".join(f"- {key.replace('_', ' ')}: {value}" for key, value in machine.items())


def write_results_md(path: Path, out: Path) -> None:
    """``docs/RESULTS.md`` from the JSON reports in ``out`` (bench, sweep, throughput, random)."""
    rel = Path(os.path.relpath(out, path.parent))
    text = io.StringIO()
    text.write(
        "# Results\n\n"
        "Generated by `cosmos bench` from the JSON reports in "
        f"`{out.as_posix()}`; never edited by hand. Regenerate it when a change moves the "
        "numbers. Definitions (success, renders, steps, wall, HTTP+queue) are in "
        "`services/bench/report.py`.\n\n"
    )
    bench = out / "bench.json"
    if bench.exists():
        data = json.loads(bench.read_text())
        text.write(section_of_bench(data, rel))
    sweep = out / "sweep.json"
    if sweep.exists():
        text.write(section_of_sweep(json.loads(sweep.read_text())))
    throughput = out / "throughput.json"
    if throughput.exists():
        text.write(section_of_throughput(json.loads(throughput.read_text())))
    random = out / "random.json"
    if random.exists():
        from services.bench.random_report import section_of_random  # it builds on this module

        text.write(section_of_random(json.loads(random.read_text())))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text.getvalue())


def _records(data: Mapping[str, Any]) -> list[SearchRecord]:
    return [SearchRecord.model_validate(r) for r in data.get("records", [])]


def section_head(title: str, data: Mapping[str, Any], *, duration: bool = False) -> str:
    """A report section's title, command, machine (and duration) and notes."""
    machine = _machine_md(data["machine"]) + "\n"
    if duration:
        machine += f"- duration: {data['duration_s']:.0f} s\n"
    notes = "".join(f"{note}\n\n" for note in data.get("notes", []))
    return f"## {title}\n\n```sh\n{data['command']}\n```\n\n{machine}\n{notes}"


def section_of_bench(data: Mapping[str, Any], plots: Path) -> str:
    text = io.StringIO()
    text.write(section_head("Searches through the local stack", data, duration=True))
    text.write(markdown_tables(summarize(_records(data))))
    text.write(
        f"\n![renders per search]({(plots / 'renders_hist.png').as_posix()})\n\n"
        f"![angle to the true pose per iteration]({(plots / 'distance.png').as_posix()})\n\n"
    )
    profile = data.get("profile")
    if profile:
        text.write(section_of_profile(profile))
    return text.getvalue()


def section_of_profile(profile: Mapping[str, Any]) -> str:
    text = io.StringIO()
    text.write("### Profile: a search against the work it cannot avoid (`--profile`)\n\n")
    text.write(profile["definition"] + "\n\n")
    header = (
        "scene",
        "searches",
        "wall p50 ms",
        "floor p50 ms",
        "one-process pipeline p50 ms",
        "wall / floor p50 (p95)",
        "stack / one process p50 (p95)",
    )
    rows = []
    for row in profile["rows"]:
        rows.append(
            [
                row["scene"],
                str(row["n"]),
                f"{row['wall_p50_ms']:.0f}",
                f"{row['floor_p50_ms']:.0f}",
                f"{row['pipeline_p50_ms']:.0f}",
                f"{row['floor_ratio_p50']:.2f} ({row['floor_ratio_p95']:.2f})",
                f"{row['stack_ratio_p50']:.2f} ({row['stack_ratio_p95']:.2f})",
            ]
        )
    text.write(md_table(header, rows) + "\n\n")
    parts = profile.get("floor_parts_p50_ms")
    if parts:
        text.write(
            "Median floor parts (ms): "
            + ", ".join(f"{k} {v:.1f}" for k, v in parts.items())
            + ".\n\n"
        )
    return text.getvalue()


def section_of_sweep(data: Mapping[str, Any]) -> str:
    text = io.StringIO()
    text.write(section_head("Render settings by measurement (`--sweep`)", data))
    detection = data.get("detection")
    if detection:
        text.write("### Detection against the renderer's ground truth, in one process\n\n")
        text.write(detection["definition"] + "\n\n")
        header = (
            "width×height",
            "spp",
            "render ms p50",
            "detect ms p50",
            "recall",
            "precision",
            "box error p50 px (at 320)",
        )
        rows = [
            [
                f"{r['width']}×{r['height']}",
                str(r["spp"]),
                f"{r['render_p50_ms']:.1f}",
                f"{r['detect_p50_ms']:.1f}",
                f"{r['recall']:.3f}",
                f"{r['precision']:.3f}",
                f"{r['box_error_p50_px']:.2f}",
            ]
            for r in detection["rows"]
        ]
        text.write(md_table(header, rows) + "\n\n")
    searches = data.get("searches")
    if searches:
        text.write("### Searches through the stack at each film width and spp\n\n")
        rows = []
        for run in searches:
            for s in summarize(_records(run)):
                rows.append(
                    [
                        str(run.get("width") or "scene"),
                        str(run["spp"]),
                        s.variant,
                        *summary_cells(s),
                    ]
                )
        text.write(md_table(("film width", "spp", "variant", *SUMMARY_COLUMNS), rows) + "\n\n")
    choice = choose_setting(searches or [])
    if choice:
        text.write(f"**Choice** ({CHOICE_RULE}): {choice}\n\n")
    return text.getvalue()


def section_of_throughput(data: Mapping[str, Any]) -> str:
    text = io.StringIO()
    text.write(section_head("Throughput (`--throughput`)", data))
    header = (
        "renderers",
        "detectors",
        "concurrent searches",
        "controller workers",
        "errors",
        "succeeded",
        "found the target",
        "wall s",
        "searches / min",
        "search wall p50 / p95 ms",
    )
    rows = [
        [
            str(r["renderers"]),
            str(r["detectors"]),
            str(r["searches"]),
            str(r["max_concurrent_searches"]),
            str(r["errors"]),
            str(r["succeeded"]),
            str(r["found"]),
            f"{r['elapsed_s']:.1f}",
            f"{r['per_minute']:.1f}",
            f"{r['wall_p50_ms']:.0f} / {r['wall_p95_ms']:.0f}",
        ]
        for r in data["rows"]
    ]
    text.write(md_table(header, rows) + "\n\n")
    return text.getvalue()
