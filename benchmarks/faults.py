"""The fault suite on a local stack: prints searches lost, peak MiB and p95 s per fault scenario.

What normal searches go through (issue 15), on real processes, when a replica dies, the only
detector is away, the controller is killed, slow clients hold sockets, 50 maximal uploads
arrive at once, and two tenants share the stack.

Run: ``.venv/bin/python -m benchmarks.faults [--quick] [--only NAME ...] [--workdir DIR]``

Each scenario (:mod:`cosmos.bench.faults.scenarios`) runs a background load of normal searches
while it injects its fault, and prints one row: searches submitted, succeeded and lost (what
counts is defined in :mod:`cosmos.bench.faults.harness`; lost must be 0), each service's peak
resident memory in MiB (the most over its replicas and restarts), the p95 latency in seconds of
the normal searches during the fault (from the first submission attempt to the end, refusals
and waits included) beside the p95 of those that ended before it, the fault's window in seconds,
and notes with the scenario's own facts. ``--quick`` shortens the loads and faults (the detector
away 5 s instead of 20 s). Every scenario runs on one local stack (2 renderers, 1 detector), in
the order of :data:`~cosmos.bench.faults.scenarios.SCENARIOS`; the exit status is 1 when a
search was lost or a scenario could not run to its end.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from cosmos.bench.faults import (
    SCENARIOS,
    ScenarioFailure,
    ScenarioResult,
    Timing,
    run_scenarios,
)

SERVICES = ("renderer", "detector", "optimizer", "controller")
HEAD = (
    f"{'scenario':<26} {'subm':>5} {'succ':>5} {'lost':>5} "
    + " ".join(f"{name[:5] + ' MiB':>9}" for name in SERVICES)
    + f" {'p95 s':>6} {'before':>6} {'fault s':>7}  notes"
)


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def row(result: ScenarioResult | ScenarioFailure) -> str:
    """One line of the table."""
    if isinstance(result, ScenarioFailure):
        return f"{result.name:<26} did not run to its end: {result.error}"
    m = result.measured
    memory = " ".join(
        f"{m.peak_rss_mib[name]:>9.0f}" if name in m.peak_rss_mib else f"{'-':>9}"
        for name in SERVICES
    )
    return (
        f"{m.name:<26} {m.counts.submitted:>5} {m.counts.succeeded:>5} {m.counts.lost:>5} "
        f"{memory} {_seconds(m.p95_s):>6} {_seconds(m.baseline_p95_s):>6} "
        f"{m.fault_s:>7.1f}  {result.notes()}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter loads and faults")
    parser.add_argument(
        "--only",
        action="append",
        choices=list(SCENARIOS),
        metavar="NAME",
        help=f"run only this scenario (again for more): {', '.join(SCENARIOS)}",
    )
    parser.add_argument("--workdir", type=Path, help="keep the stacks' databases and logs here")
    args = parser.parse_args(argv)
    timing = Timing.quick() if args.quick else Timing()
    started = time.monotonic()
    results: list[ScenarioResult | ScenarioFailure] = []
    with tempfile.TemporaryDirectory(prefix="cosmos-faults-") as scratch:
        workdir = args.workdir or Path(scratch)
        for result in run_scenarios(workdir, timing, args.only):
            print(f"  {result.name} done after {time.monotonic() - started:.0f} s", file=sys.stderr)
            results.append(result)
    print(f"fault suite ({'quick' if args.quick else 'full'}), {time.monotonic() - started:.0f} s")
    print(HEAD)
    for result in results:
        print(row(result))
    failed = any(isinstance(r, ScenarioFailure) or r.measured.counts.lost for r in results)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
