"""``cosmos bench``: the paper's evaluation run through the real services, end to end.

Three modes, each writing a JSON report into ``--out`` and regenerating ``--results-md`` from
every report there:

* the bench (default): ``n`` seeded targets per scene and variant, each searched by every
  strategy from the same random start, through a local stack started on free ports (or a running
  one at ``--url``); tables, eq. 9, plots; with ``--profile`` also the floor of a search
  (:mod:`cosmos.bench.profile`). Report: ``bench.json``.
* ``--sweep 4,8,16``: render settings by measurement. Detection against the renderer's exact
  ground truth at each spp and film width, in one process; then the bench's searches through a
  stack whose controller renders at each spp. Report: ``sweep.json``.
* ``--throughput``: ``--throughput-searches`` searches submitted at once to a stack with one
  renderer and detector, then to one with ``--renderers``/``--detectors`` replicas; searches
  per minute. Report: ``throughput.json``.
* ``--free``: free-camera targets on the ``--scenes`` and ``--random-scenes N`` generated ones,
  searched with ``mode=free`` beside a plain ``solvePnPRansac`` baseline and the box-only bound
  (:mod:`cosmos.bench.free_run`), resumable in ``--chunk-minutes`` chunks. Report:
  ``free.json``.
* ``--random-scenes N``: N generated scenes, searched with the general detector, then again with
  each scene's own after onboarding it (:mod:`cosmos.bench.random_run`). Report:
  ``random.json``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from cosmos.bench.machine import machine_info
from cosmos.bench.plots import write_plots
from cosmos.bench.profile import profile_searches, profile_summary
from cosmos.bench.random_report import band_cells, band_table
from cosmos.bench.results_md import write_results_md
from cosmos.bench.runner import BenchTarget, make_targets, run_searches
from cosmos.bench.session import (
    BenchConfig,
    load_at_end,
    open_endpoints,
    say,
    search_all,
    services_info,
    write_report,
)
from cosmos.bench.stats import percentile, strategy_label, summarize
from cosmos.bench.tables import text_tables
from services.common.contracts.optimize import StrategyName

__all__ = ["run", "run_main", "run_sweep", "run_throughput"]


def run_main(config: BenchConfig) -> int:
    """The bench: searches, tables, plots, and the profile when asked."""
    started = time.perf_counter()
    with open_endpoints(config, spp=config.spp, width=config.width) as endpoints:
        machine = machine_info(services_info(endpoints, config.spp, config.width))
        targets, records = search_all(config, endpoints, config.variants, config.strategies)
        summaries = summarize(records)
        say("")
        say(text_tables(summaries))
        say("\nby θ band (found; given start = the bench's random one, the paper's protocol)")
        say(band_table(band_cells(records, strategy_label), title="strategy"))
        profile = None
        if config.profile:
            sample = _profile_sample(targets, config)
            say(f"\nprofile: {len(sample)} clean on-grid targets, reprojection")
            samples = profile_searches(
                endpoints.controller,
                sample,
                render_spp=config.spp,
                render_width=config.width,
                max_iterations=config.max_iterations,
                progress=say if config.verbose else None,
                api_key=endpoints.api_key,
            )
            profile = profile_summary(samples)
            for row in profile["rows"]:
                say(
                    f"  {row['scene']:<8} n={row['n']:<3} wall p50 {row['wall_p50_ms']:.0f} ms, "
                    f"floor p50 {row['floor_p50_ms']:.0f} ms, one process p50 "
                    f"{row['pipeline_p50_ms']:.0f} ms; median wall/floor "
                    f"{row['floor_ratio_p50']:.2f} (goal ≤ 1.3), median stack/one process "
                    f"{row['stack_ratio_p50']:.2f} (goal ≤ 1.1)"
                )
    duration = time.perf_counter() - started
    report: dict[str, Any] = {
        "command": config.command,
        "machine": machine | load_at_end(),
        "duration_s": duration,
        "config": {
            "n": config.n,
            "scenes": config.scenes,
            "strategies": config.strategies,
            "variants": config.variants,
            "starts": config.starts,
            "seed": config.seed,
            "spp": config.spp,
            "width": config.width,
            "concurrency": config.concurrency,
            "max_iterations": config.max_iterations,
        },
        "notes": list(config.notes),
        "summaries": [vars(s) | {"success_rate": s.success_rate} for s in summaries],
        "records": [r.model_dump(mode="json") for r in records],
        "profile": profile,
    }
    config.out.mkdir(parents=True, exist_ok=True)
    for path in write_plots(records, config.out):
        say(f"wrote {path}")
    write_report(config, "bench.json", report)
    errors = sum(r.status == "error" for r in records)
    return 1 if errors else 0


def _profile_sample(targets: Sequence[BenchTarget], config: BenchConfig) -> list[BenchTarget]:
    """The first ``profile_n`` clean on-grid targets of each scene."""
    sample: list[BenchTarget] = []
    for scene in config.scenes:
        clean = [t for t in targets if t.scene == scene and t.variant == "clean"]
        sample.extend(clean[: config.profile_n])
    return sample


# -- sweep ----------------------------------------------------------------------------------


def run_sweep(config: BenchConfig) -> int:
    """Render settings by measurement: detection quality per (spp, width), searches per spp."""
    from cosmos.bench.settings_sweep import detection_sweep

    started = time.perf_counter()
    say(f"detection against ground truth: {config.sweep_poses} poses per scene")
    detection = detection_sweep(
        config.scenes, spps=config.sweep, poses=config.sweep_poses, seed=config.seed, say=say
    )
    searches = []
    machine: dict[str, Any] = {}
    for width in config.sweep_widths or (None,):
        for spp in config.sweep:
            with open_endpoints(config, spp=spp, width=width) as endpoints:
                machine = machine or machine_info(services_info(endpoints, None, None))
                _, records = search_all(config, endpoints, config.variants, config.strategies)
            say(f"\nsearch views at {spp} spp, {width or 'the scene'}'s width")
            say(text_tables(summarize(records)))
            searches.append(
                {
                    "spp": spp,
                    "width": width,
                    "records": [r.model_dump(mode="json") for r in records],
                }
            )
    report = {
        "command": config.command,
        "machine": machine | load_at_end() | {"duration_s": round(time.perf_counter() - started)},
        "notes": list(config.notes),
        "detection": detection,
        "searches": searches,
    }
    write_report(config, "sweep.json", report)
    return 0


# -- throughput -----------------------------------------------------------------------------


def run_throughput(config: BenchConfig) -> int:
    """``throughput_searches`` searches at once: one replica per stage, then the replicas asked."""
    started = time.perf_counter()
    rows = []
    machine: dict[str, Any] = {}
    failures = 0
    for renderers, detectors in ((1, 1), (config.renderers, config.detectors)):
        with open_endpoints(
            config,
            spp=config.spp,
            width=config.width,
            renderers=renderers,
            detectors=detectors,
        ) as ep:
            machine = machine or machine_info(services_info(ep, config.spp, config.width))
            scenes = config.scenes
            per_scene = -(-config.throughput_searches // len(scenes))
            targets = make_targets(
                ep.renderer, scenes, ("clean",), per_scene, config.seed, token=ep.service_token
            )
            jobs: list[tuple[BenchTarget, StrategyName]] = [(t, "reprojection") for t in targets]
            jobs = jobs[: config.throughput_searches]
            ep.warm(scenes)
            run_searches(
                ep.controller, jobs[:1], max_iterations=config.max_iterations, api_key=ep.api_key
            )
            t0 = time.perf_counter()
            records = run_searches(
                ep.controller,
                jobs,
                concurrency=len(jobs),
                max_iterations=config.max_iterations,
                api_key=ep.api_key,
            )
            elapsed = time.perf_counter() - t0
        errors = sum(r.status == "error" for r in records)
        failures += errors
        walls = [r.wall_ms for r in records]
        row = {
            "renderers": renderers,
            "detectors": detectors,
            "searches": len(records),
            "max_concurrent_searches": config.max_concurrent_searches or "default (4)",
            "errors": errors,
            "succeeded": sum(r.status == "succeeded" for r in records),
            "found": sum(r.success for r in records),
            "elapsed_s": elapsed,
            "per_minute": 60.0 * len(records) / elapsed,
            "wall_p50_ms": percentile(walls, 50),
            "wall_p95_ms": percentile(walls, 95),
        }
        rows.append(row)
        say(
            f"{renderers} renderer(s), {detectors} detector(s): {len(records)} searches at once in "
            f"{elapsed:.1f} s = {row['per_minute']:.1f} searches/min, {errors} errors, "
            f"{row['found']} found the target"
        )
    report = {
        "command": config.command,
        "machine": machine | load_at_end() | {"duration_s": round(time.perf_counter() - started)},
        "notes": list(config.notes),
        "rows": rows,
    }
    write_report(config, "throughput.json", report)
    return 1 if failures else 0


def run(config: BenchConfig) -> int:
    """Run the mode ``config`` asks for; the exit status (1 if any search errored)."""
    if config.regenerate:
        if config.results_md is None:
            raise ValueError("--regenerate needs --results-md")
        write_results_md(config.results_md, config.out)
        say(f"wrote {config.results_md} from the reports in {config.out}")
        return 0
    if config.n < 1:
        raise ValueError("--n must be at least 1")
    if config.free:
        from cosmos.bench.free_run import run_free

        return run_free(config)
    if config.random_scenes:
        from cosmos.bench.random_run import run_random

        return run_random(config)
    if config.sweep:
        return run_sweep(config)
    if config.throughput:
        return run_throughput(config)
    return run_main(config)
