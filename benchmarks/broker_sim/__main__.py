"""``python -m benchmarks.broker_sim``: the sweep, its table, and ``docs/results/broker_sim.json``.

Options: ``--sizes 1,4,16`` (renderers), ``--searches N`` per case, ``--seed``, ``--out PATH``
('' writes nothing). Regenerate ``docs/RESULTS.md`` after with ``cosmos bench --regenerate``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from benchmarks.broker_sim import ASSUMPTIONS
from benchmarks.broker_sim.model import DEFAULT_POLICY, ORACLE, P2C
from benchmarks.broker_sim.sweep import SCENARIOS, SweepConfig, goal_met, sweep
from benchmarks.broker_sim.workload import TaskLengths

OUT = Path("docs/results/broker_sim.json")
HEADER = (
    f"{'scenario':8} {'r/d/o':>11} {'policy':30} {'p50 ms':>8} {'p99 ms':>8} {'searches/s':>10} "
    f"{'p99÷p2c':>8} {'p99÷oracle':>10}"
)


def lines(row: dict[str, Any]) -> list[str]:
    """The table's lines of one case: a line per policy (the default starred), then the goal."""
    results = row["policies"]
    sizes = f"{row['renderer']}/{row['detector']}/{row['optimizer']}"
    out = []
    for policy, r in results.items():
        name = policy + ("*" if policy == DEFAULT_POLICY else "")
        vs_p2c = r["p99_ms"] / results[P2C]["p99_ms"] if P2C in results else float("nan")
        vs_oracle = r["p99_ms"] / results[ORACLE]["p99_ms"] if ORACLE in results else float("nan")
        out.append(
            f"{row['scenario']:8} {sizes:>11} {name:30} {r['p50_ms']:8.0f} {r['p99_ms']:8.0f} "
            f"{r['per_s']:10.2f} {vs_p2c:8.2f} {vs_oracle:10.2f}"
        )
    if {DEFAULT_POLICY, P2C, ORACLE} <= results.keys():
        out.append(f"{'':21} goal {'met' if goal_met(row)['met'] else 'MISSED'}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.broker_sim")
    defaults = SweepConfig()
    parser.add_argument("--sizes", default=",".join(map(str, defaults.sizes)))
    parser.add_argument("--searches", type=int, default=defaults.searches)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args(argv)
    config = SweepConfig(
        sizes=tuple(int(s) for s in args.sizes.split(",")), searches=args.searches, seed=args.seed
    )
    tasks = TaskLengths.load()
    started = time.perf_counter()
    print("\n".join(f"- {a}" for a in ASSUMPTIONS))
    print(HEADER, flush=True)
    rows = sweep(config, tasks, lambda row: print("\n".join(lines(row)), flush=True))
    goals = [goal_met(row) for row in rows]
    missed = [
        f"{r['scenario']} {r['renderer']}" for r, g in zip(rows, goals, strict=True) if not g["met"]
    ]
    print(
        f"{DEFAULT_POLICY}: p99 ÷ p2c at most {max(g['vs_p2c'] for g in goals):.2f}, p99 ÷ oracle "
        f"at most {max(g['vs_oracle'] for g in goals):.2f}; goal missed at "
        f"{', '.join(missed) or 'no size'} ({time.perf_counter() - started:.0f} s)"
    )
    if args.out:
        argv_text = " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        report = {
            "command": f"python -m benchmarks.broker_sim {argv_text}".strip(),
            "assumptions": list(ASSUMPTIONS),
            "scenarios": SCENARIOS,
            "default_policy": DEFAULT_POLICY,
            "config": asdict(config),
            "tasks": {
                "command": tasks.source["command"],
                "sources": tasks.source["sources"],
                "tasks_measured": tasks.source["tasks_measured"],
            },
            "rows": [row | {"goal": goal} for row, goal in zip(rows, goals, strict=True)],
        }
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
