"""Free-bench runs of several seeds side by side: how the free camera generalises.

Run: ``.venv/bin/python -m benchmarks.free_seeds out/seed1/free.json out/seed2/free.json …``

Each file is a ``cosmos bench --free`` report (``free.json``), for example of
``cosmos bench --free --scene demo --random-scenes 2 --n 8 --seed S --out out/seedS
--results-md ''`` for S = 1…6; a run with ``--onboard default`` also holds its generated
scenes searched with their own models. One seed's scenes and cameras are one draw: the figures
that ``docs/RESULTS.md`` shows for seed 1 are not those of every draw. Per run and in total,
and per detector (``own``: a built-in scene's or an onboarded scene's model; ``general``: the
shipped shape model on a generated scene), it prints over the clean, JPEG and noise variants
the share within 5 % of the radius and 2° (the goal's measure) with the fov given and not,
the share of box estimates within 10 % / 5°, and per elevation band with the fov given and not;
the share within 5 % / 2° of the ``photo`` and ``changed`` variants (fov given or not, the
goal's measure for them); then over every variant the confirmed answers (``found``), how many
of them are wrong, and the renders a search.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

from cosmos.bench.free_bench.records import ANSWER, BOXES, FreeRecord
from cosmos.bench.free_bench.report import confirmed_wrong, within
from cosmos.bench.free_targets.draw import BANDS
from cosmos.bench.free_targets.metrics import THRESHOLDS

FITTING = ("clean", "jpeg", "noise")
ALTERED = ("photo", "changed")


def _share(records: Sequence[FreeRecord], method: str, limit: tuple[float, float]) -> str:
    if not records:
        return "—"
    hits = round(within(records, method, limit) * len(records))
    return f"{hits}/{len(records)}"


def _mean_renders(records: Sequence[FreeRecord]) -> str:
    return f"{sum(r.renders for r in records) / len(records):.2f}" if records else "—"


def _row(label: str, records: Sequence[FreeRecord]) -> str:
    fitting = [r for r in records if r.variant in FITTING]
    given = [r for r in fitting if r.intrinsics_given]
    unknown = [r for r in fitting if not r.intrinsics_given]
    altered = [r for r in records if r.variant in ALTERED]
    return (
        f"{label:<40} given {_share(given, ANSWER, THRESHOLDS[1]):>7}  "
        f"boxes {_share(given, BOXES, THRESHOLDS[2]):>7}  "
        f"not given {_share(unknown, ANSWER, THRESHOLDS[1]):>7}  "
        f"photo/changed {_share(altered, ANSWER, THRESHOLDS[1]):>7}  "
        f"confirmed {sum(r.outcome == 'found' for r in records):>3}, wrong "
        f"{len(confirmed_wrong(records))}  renders {_mean_renders(records)}  "
        f"| given by band: {_bands(given)} | not given by band: {_bands(unknown)}"
    )


def _bands(records: Sequence[FreeRecord]) -> str:
    return "  ".join(
        f"{band} {_share([r for r in records if r.band == band], ANSWER, THRESHOLDS[1])}"
        for band in BANDS
    )


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", help="free.json files of cosmos bench --free")
    args = parser.parse_args(argv)
    runs = []
    for path in args.reports:
        if not Path(path).is_file():
            parser.error(f"{path}: no such report (a run still going writes it at its end)")
        report = json.loads(Path(path).read_text())
        records = [FreeRecord.model_validate(r) for r in report["records"]]
        runs.append((str(report["config"]["seed"]), records))
    seeds = [seed for seed, _ in runs]
    if len(set(seeds)) < len(seeds):  # one seed run twice: name each run by its file too
        runs = [(f"{s} ({p})", r) for (s, r), p in zip(runs, args.reports, strict=True)]
    print("within 5 %/2° (clean, JPEG, noise); boxes: the box estimate within 10 %/5°")
    everything: list[FreeRecord] = []
    for seed, records in runs:
        everything += records
        for detector in ("own", "general"):
            mine = [r for r in records if r.detector == detector]
            if mine:
                print(_row(f"seed {seed} {detector}", mine))
    for detector in ("own", "general"):
        mine = [r for r in everything if r.detector == detector]
        if mine:
            print(_row(f"all seeds {detector}", mine))
    print(_row("all seeds", everything))


if __name__ == "__main__":
    main()
