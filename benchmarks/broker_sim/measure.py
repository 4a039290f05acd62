"""The simulation's task lengths and search shapes, measured from real searches.

Run: ``.venv/bin/python -m benchmarks.broker_sim.measure [REPORT.json ...]`` (default: the
bench's reports ``docs/results/bench.json`` and ``docs/results/random.json``); writes
``benchmarks/broker_sim/tasks.json``, which the simulation reads, so it runs without rendering.

The bench's reports hold, per search through the real stack, the stage timings every iteration
records (:class:`~services.common.contracts.search.StageTimings`: what the controller waited
for each render, detection and optimizer call, HTTP included, one search at a time). Kept: the
searches of the default strategy (``reprojection``) that have a trajectory, on the built-in
and the generated scenes. Stored: per kind of task the 0th…100th percentiles of its lengths (ms),
and how many searches had each (renders, iterations): a pose seen before is neither rendered
nor detected again, so a search may iterate more than it renders.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DEFAULT_REPORTS", "TASKS_JSON", "measure"]

TASKS_JSON = Path(__file__).with_name("tasks.json")
DEFAULT_REPORTS = ("docs/results/bench.json", "docs/results/random.json")
STRATEGY = "reprojection"
KINDS = {"render": "render_ms", "detect": "detect_ms", "optimize": "optimize_ms"}


def _searches(report: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [
        r
        for r in report.get("records", [])
        if r.get("strategy") == STRATEGY and r.get("trajectory") and r.get("renders")
    ]


def measure(reports: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The task-length percentiles and search shapes of the ``reports`` (path -> report)."""
    lengths: dict[str, list[float]] = {kind: [] for kind in KINDS}
    shapes: Counter[tuple[int, int]] = Counter()
    sources = []
    for path, report in reports.items():
        searches = _searches(report)
        sources.append(
            {
                "report": path,
                "command": report.get("command"),
                "commit": report.get("machine", {}).get("commit"),
                "date_utc": report.get("machine", {}).get("date_utc"),
                "searches": len(searches),
            }
        )
        for search in searches:
            shapes[(int(search["renders"]), len(search["trajectory"]))] += 1
            for step in search["trajectory"]:
                for kind, key in KINDS.items():
                    if step[key] > 0:  # 0: a view seen before, not rendered nor detected
                        lengths[kind].append(float(step[key]))
    if not shapes:
        raise ValueError(f"no {STRATEGY} search with a trajectory in {', '.join(reports)}")
    return {
        "command": "python -m benchmarks.broker_sim.measure " + " ".join(reports),
        "definition": __doc__.split("\n\n", 2)[2].strip() if __doc__ else "",
        "sources": sources,
        "task_ms_percentiles": {
            kind: [round(float(q), 2) for q in np.percentile(values, np.arange(101))]
            for kind, values in lengths.items()
        },
        "tasks_measured": {kind: len(values) for kind, values in lengths.items()},
        "shapes": [
            {"renders": renders, "iterations": iterations, "searches": count}
            for (renders, iterations), count in sorted(shapes.items())
        ],
    }


def _read(paths: Iterable[str]) -> dict[str, Mapping[str, Any]]:
    return {path: json.loads(Path(path).read_text()) for path in paths}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    parser.add_argument("reports", nargs="*", default=list(DEFAULT_REPORTS))
    parser.add_argument("--out", type=Path, default=TASKS_JSON)
    args = parser.parse_args(argv)
    tasks = measure(_read(args.reports))
    args.out.write_text(json.dumps(tasks, indent=1) + "\n")
    counts = ", ".join(f"{n} {kind}s" for kind, n in tasks["tasks_measured"].items())
    searches = sum(source["searches"] for source in tasks["sources"])
    print(f"wrote {args.out}: {counts} from {searches} searches")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
