"""Next-pose strategies in the simulator: prints success, moves per search and paper eq. 9.

Run: ``.venv/bin/python -m benchmarks.strategies [--scene demo] [--starts 8] [--noise]``

Detections come from :class:`simulation.SceneSimulator` (no renderer). For each scene, grid and
strategy every grid pose is a target; ``simple`` and ``paper`` start from *every* grid pose (their
decisions depend only on the current view and the target, so each (decision, target) is computed
once and reused, which keeps all pairs affordable), the map-based ``reprojection`` from a seeded
sample of ``--starts`` poses per target plus the pose farthest from it. Grids: the scene's own and
the full π/24 grid (7.5°, θ 0–90°).

Columns: ``success`` — the strategy declared the search done with the camera at the target;
``iterations`` — moves after the start view until the camera first sat at the target (mean /
p95 / max over successful searches; the paper's count); ``to done`` — mean moves until it
declared done; ``wrong`` — declared done elsewhere; ``lost`` — hit the move limit (60) or a cycle
(a pose entered a fourth time); ``ambig.`` — searches with an answer flagged ambiguous.
``--noise`` adds a table with 1 px box noise, 5 % missed and 5 % spurious detections. Targets are
split over ``--jobs`` worker processes (default: one per CPU); each target draws from its own
seeded generator, so the figures do not depend on the split.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Hashable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.geometry.grid import HemisphereGrid, grid_for
from services.common.geometry.scene import LoadedScene
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer.calibration import CalibrationStore
from services.optimizer.problem import Plan
from services.optimizer.strategies import STRATEGIES
from simulation import NoiseModel, SceneSimulator, SearchOutcome, run_search

ALL_PAIRS = ("simple", "paper")
PAPER_SIMPLE_WORST = 36
PAPER_OPTIMISED = 2


@dataclass(frozen=True)
class Row:
    scene: str
    grid: str
    strategy: str
    starts: str
    outcomes: list[SearchOutcome]
    seconds: float

    @property
    def arrivals(self) -> np.ndarray:
        return np.array([o.arrival for o in self.outcomes if o.success], dtype=float)

    def line(self) -> str:
        n = len(self.outcomes)
        ok = self.arrivals
        success = 100.0 * len(ok) / n if n else math.nan
        wrong = sum(o.done and not o.success for o in self.outcomes)
        lost = sum(not o.done for o in self.outcomes)
        ambiguous = sum(o.ambiguous for o in self.outcomes)
        to_done = np.mean([o.moves for o in self.outcomes if o.success]) if len(ok) else math.nan
        its = (
            f"{ok.mean():6.2f} {np.percentile(ok, 95):5.1f} {ok.max():4.0f}"
            if len(ok)
            else f"{'—':>6} {'—':>5} {'—':>4}"
        )
        return (
            f"{self.scene:>7} {self.grid:>13} {self.strategy:>13} {self.starts:>10} {n:>7} "
            f"{success:7.2f}% {its} {to_done:7.2f} {wrong:>6} {lost:>5} {ambiguous:>6} "
            f"{self.seconds:6.0f} s"
        )


HEADER = (
    f"{'scene':>7} {'grid':>13} {'strategy':>13} {'starts':>10} {'runs':>7} {'success':>8} "
    f"{'iterations mean/p95/max':>16} {'to done':>7} {'wrong':>6} {'lost':>5} {'ambig.':>6} "
    f"{'time':>8}"
)


def oracle_worst(grid: HemisphereGrid) -> int:
    """Moves of the step-by-step search with a perfect estimate, worst over all pairs:
    latitude moves (keeping the nearest longitude, as the grid's N/S neighbours do), then the
    shorter way around the target ring."""
    worst = 0
    for start in range(grid.size):
        index = grid.unflat(start)
        for lat in range(grid.ring_count):
            here = index
            while here.lat != lat:
                step = grid.neighbour(here, "S" if lat > here.lat else "N")
                if step is None:
                    break
                here = step
            n = grid.ring_size(lat)
            ring = max(min((lon - here.lon) % n, (here.lon - lon) % n) for lon in range(n))
            worst = max(worst, abs(lat - index.lat) + ring)
    return worst


@dataclass(frozen=True)
class Job:
    """One row's work for a chunk of targets (picklable for worker processes)."""

    scene: str
    step_deg: float
    min_theta_deg: float
    max_theta_deg: float
    strategy: str
    targets: tuple[int, ...]
    starts: int | None
    noise: NoiseModel | None
    tolerance_px: float
    seed: int


def run_job(job: Job) -> list[SearchOutcome]:
    """Every target of the job from every start, or from ``starts`` seeded ones plus the pose
    farthest from the target. Each target has its own generator, so chunking changes nothing."""
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get(job.scene)
    simulator = _simulator(job.scene, scene)
    calibration = CalibrationStore.load().find(scene.spec.camera)
    grid = grid_for(job.step_deg, job.min_theta_deg, job.max_theta_deg)
    units = pose_to_cartesian(grid.theta_deg, grid.phi_deg)
    cache: dict[Hashable, Plan] | None = (
        {} if STRATEGIES[job.strategy].decision_key is not None and job.noise is None else None
    )
    outcomes = []
    for target in job.targets:
        rng = np.random.default_rng([job.seed, target])
        if job.starts is None:
            chosen: Sequence[int] = range(grid.size)
        else:
            farthest = int(np.argmin(units @ units[target]))
            sample = rng.choice(grid.size, size=min(job.starts, grid.size), replace=False)
            chosen = [farthest, *(int(s) for s in sample)]
        for start in chosen:
            outcomes.append(
                run_search(
                    job.strategy,
                    simulator,
                    grid,
                    target,
                    int(start),
                    calibration=calibration,
                    noise=job.noise,
                    rng=rng,
                    tolerance_px=job.tolerance_px,
                    cache=cache,
                )
            )
    return outcomes


_SIMULATORS: dict[str, SceneSimulator] = {}


def _simulator(scene_id: str, scene: LoadedScene) -> SceneSimulator:
    """One simulator per scene and process (it caches its grid views)."""
    if scene_id not in _SIMULATORS:
        _SIMULATORS[scene_id] = SceneSimulator.from_scene(scene)
    return _SIMULATORS[scene_id]


def run_row(
    pool: ProcessPoolExecutor | None,
    scene: str,
    grid_name: str,
    grid: HemisphereGrid,
    strategy: str,
    starts: int | None,
    noise: NoiseModel | None,
    tolerance_px: float,
    seed: int,
    chunks: int,
) -> Row:
    """One table row: every target of ``grid``, split into ``chunks`` jobs over the pool."""
    started = time.perf_counter()
    step, lo, hi = grid.angle_step_deg, float(grid.theta_deg[0]), float(grid.theta_deg[-1])
    jobs = [
        Job(scene, step, lo, hi, strategy, tuple(int(t) for t in part), starts, noise,
            tolerance_px, seed)
        for part in np.array_split(np.arange(grid.size), chunks)
    ]  # fmt: skip
    results = pool.map(run_job, jobs) if pool is not None else map(run_job, jobs)
    outcomes = [o for part in results for o in part]
    label = "all" if starts is None else f"{starts}+far"
    return Row(scene, grid_name, strategy, label, outcomes, time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", help="scene id (default: demo)")
    parser.add_argument(
        "--starts", type=int, default=6, help="seeded starts per target for reprojection"
    )
    parser.add_argument(
        "--sample-all",
        type=int,
        default=None,
        help="sample this many starts per target for simple/paper too (default: all starts)",
    )
    parser.add_argument("--noise", action="store_true", help="add a table with noisy detections")
    parser.add_argument(
        "--noise-starts", type=int, default=1, help="seeded starts per target with noise"
    )
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument(
        "--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: CPUs)"
    )
    args = parser.parse_args()
    pool = ProcessPoolExecutor(args.jobs) if args.jobs > 1 else None
    chunks = 4 * args.jobs
    scenes = args.scene or ["demo"]
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    rows: list[Row] = []
    print("next-best-pose strategies in the offline simulator (noise-free detections)")
    print(HEADER, flush=True)
    for scene_id in scenes:
        scene = catalog.get(scene_id)
        own = scene.spec.search.grid()
        grids = [(f"{own.angle_step_deg:g}° {own.theta_deg[0]:g}–{own.theta_deg[-1]:g}", own)]
        grids.append(("π/24 0–90", grid_for(7.5, 0.0, 90.0)))
        for grid_name, grid in grids:
            for strategy in STRATEGIES:
                starts = args.sample_all if strategy in ALL_PAIRS else args.starts
                row = run_row(
                    pool, scene_id, grid_name, grid, strategy, starts, None, 1.0, args.seed,
                    chunks,
                )  # fmt: skip
                rows.append(row)
                print(row.line(), flush=True)
    if args.noise:
        noise = NoiseModel(pixel_sigma=1.0, miss_rate=0.05, spurious_rate=0.05, colour_sigma=4.0)
        print(
            "\nnoisy detections: σ = 1 px per box edge, 5 % missed, 5 % spurious, colour σ = 4; "
            "tolerance 1.5 px"
        )
        print(HEADER, flush=True)
        for scene_id in scenes:
            grid = catalog.get(scene_id).spec.search.grid()
            for strategy in STRATEGIES:
                row = run_row(
                    pool, scene_id, "scene grid", grid, strategy, args.noise_starts, noise, 1.5,
                    args.seed, chunks,
                )  # fmt: skip
                print(row.line(), flush=True)

    if pool is not None:
        pool.shutdown()
    print("\npaper eq. 9: improvement = (optimised − step-by-step) / step-by-step")
    full = grid_for(7.5, 0.0, 90.0)
    print(
        f"  paper:    ({PAPER_OPTIMISED} − {PAPER_SIMPLE_WORST}) / {PAPER_SIMPLE_WORST} = "
        f"{(PAPER_OPTIMISED - PAPER_SIMPLE_WORST) / PAPER_SIMPLE_WORST:+.2%}"
    )
    print(f"  step-by-step with a perfect estimate, worst case on π/24: {oracle_worst(full)} moves")
    for scene_id in scenes:
        by = {r.strategy: r for r in rows if r.scene == scene_id and r.grid == "π/24 0–90"}
        simple = by["simple"].arrivals
        if not len(simple):
            continue
        worst = float(simple.max())
        for optimised in ("paper", "reprojection"):
            arr = by[optimised].arrivals
            if not len(arr):
                continue
            best, mean = float(arr.max()), float(simple.mean())
            print(
                f"  {scene_id} π/24, {optimised:>12} vs simple: as the paper pairs them (mean "
                f"against worst) ({arr.mean():.2f} − {worst:.0f}) / {worst:.0f} = "
                f"{(arr.mean() - worst) / worst:+.2%}; worst against worst ({best:.0f} − "
                f"{worst:.0f}) / {worst:.0f} = {(best - worst) / worst:+.2%}; mean against mean "
                f"({arr.mean():.2f} − {mean:.2f}) / {mean:.2f} = {(arr.mean() - mean) / mean:+.2%}"
            )


if __name__ == "__main__":
    main()
