"""``cosmos bench --free``: free targets searched through the real stack (issue 23, item 5).

1. ``--random-scenes N`` scenes are generated as the random-scene bench generates them (scene
   ``i`` from the seed ``[seed, i]``) into a folder the local stack reads, beside the built-in
   ``--scenes``; they are searched with the general detector (not onboarded). With
   ``--onboard tiny|default`` each is then onboarded as a user would (``cosmos scenes add``:
   :func:`cosmos.bench.random_run.onboarder`), and once the detector serves its own model its
   targets are searched again with it (records ``onboarded``). The models stay beside the
   scenes: a run that resumes in the same ``--scenes-out`` after onboarding began has its
   general arm done already, but a new run there would search them with their own.
2. Per scene, ``--n`` free targets are drawn (:func:`cosmos.bench.free_targets.draw_targets`:
   distance, elevation with nadir views, roll, fov ±30 %, a third without their intrinsics, at
   least three objects 60 % visible) and rendered by the stack's renderer, on the scene
   camera's film or ``--target-width`` pixels wide at its aspect (a drone's photo is larger than
   the search's views); each gets its image of every variant (:mod:`.free_bench.targets`) and its
   box-only bound.
3. Each image is searched with ``POST /searches?mode=free`` (``fov_deg`` when given), one at a
   time, then its floor is timed and the baseline run on the search's detections
   (:mod:`.free_bench.searching`); the record is appended to the checkpoint
   (:mod:`.free_bench.checkpoint`).
4. The tables (:mod:`.free_bench.report`) go to the terminal, ``free.json`` and ``docs/RESULTS.md``.

``--chunk-minutes M`` stops starting searches after M minutes and writes a partial report; the
same command resumes from the checkpoint.
"""

from __future__ import annotations

import asyncio
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np

from cosmos.bench.free_bench.checkpoint import Checkpoint, Key
from cosmos.bench.free_bench.records import FreeRecord
from cosmos.bench.free_bench.report import (
    free_tables,
    goal_checks_by_detector,
    time_line,
    wrong_line,
)
from cosmos.bench.free_bench.searching import StackCalls, search_target
from cosmos.bench.free_bench.targets import VariantImage, variant_image
from cosmos.bench.free_targets.draw import (
    FOV_RANGE,
    ROLL_LIMIT_DEG,
    DrawError,
    FreeTarget,
    draw_targets,
    target_film,
)
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solve import box_only_bound
from cosmos.bench.machine import machine_info
from cosmos.bench.random_run import onboarder, onboarding_summary, wait_for_model
from cosmos.bench.runner import TARGET_SPP
from cosmos.bench.scenes import generate_scene
from cosmos.bench.session import (
    BenchConfig,
    Endpoints,
    load_at_end,
    open_endpoints,
    say,
    services_info,
    write_report,
)
from services.optimizer.free import SceneObjects, scene_objects
from services.renderer.client import RendererClient

__all__ = ["CHECKPOINT", "run_free"]

CHECKPOINT = "free.checkpoint.jsonl"
Job = tuple[FreeTarget, VariantImage, Estimate]


def _fingerprint(config: BenchConfig, scenes: Sequence[str]) -> dict[str, Any]:
    return {
        "onboard": config.onboard,
        "scenes": list(scenes),
        "n": config.n,
        "seed": config.seed,
        "variants": list(config.variants),
        "spp": config.spp,
        "width": config.width,
        "target_width": config.target_width,
        "target_aspect": list(config.target_aspect) if config.target_aspect else None,
        "roll_limit": _roll_limit(config),
        "fov_range": list(_fov_range(config)),
        "max_iterations": config.max_iterations,
    }


def _fov_range(config: BenchConfig) -> tuple[float, float]:
    """The targets' fov range: ``--fov-range``, else the draw's own."""
    return config.fov_range or FOV_RANGE


def _roll_limit(config: BenchConfig) -> float:
    """The targets' roll limit: ``--roll-limit``, else the draw's own."""
    return ROLL_LIMIT_DEG if config.roll_limit is None else config.roll_limit


def _jobs(
    config: BenchConfig,
    ep: Endpoints,
    scene_id: str,
    done: dict[Key, FreeRecord],
    notes: list[str],
    onboarded: bool = False,
) -> list[Job]:
    """The scene's targets not searched yet (with an ``onboarded`` model or not), drawn and made
    in every variant still to do."""

    def todo(variant: str, index: int) -> bool:
        return (scene_id, variant, index, onboarded) not in done

    pending = {i for i in range(config.n) if any(todo(v, i) for v in config.variants)}
    if not pending:
        return []
    scene = ep.scene_of(scene_id)
    shapes = scene_shapes(scene)
    width, height = target_film(config.target_width, config.target_aspect, scene.spec.camera.width)
    jobs: list[Job] = []
    with RendererClient(ep.renderer, token=ep.service_token) as renderer:
        try:
            targets = draw_targets(
                renderer, scene, shapes, config.n, config.seed,
                width=width, height=height, spp=TARGET_SPP, only=pending,
                fov_range=_fov_range(config), roll_limit=_roll_limit(config),
            )  # fmt: skip
        except DrawError as exc:
            notes.append(f"skipped {scene_id}: {exc}")
            say(notes[-1])
            return []
        for target in targets:
            rng = np.random.default_rng([config.seed, target.index, 1])  # as free_targets' own
            bound = box_only_bound(target, shapes, rng)
            for variant in config.variants:
                if not todo(variant, target.index):
                    continue
                image = variant_image(
                    renderer, scene, target, variant, config.seed,
                    altered_dir=ep.altered_dir, spp=TARGET_SPP,
                )  # fmt: skip
                if image is None:
                    notes.append(f"{scene_id} {variant} #{target.index}: no copy could be rendered")
                    continue
                jobs.append((target, image, bound))
    say(f"{scene_id}: {len(targets)} targets drawn, {len(jobs)} searches to run")
    return jobs


async def _search_jobs(
    calls: StackCalls,
    jobs: Sequence[Job],
    objects: SceneObjects,
    arm: tuple[bool, bool],
    checkpoint: Checkpoint,
    deadline: float,
    verbose: bool,
) -> bool:
    """Search every job one at a time, checkpointing each; False when the deadline stopped it.
    ``arm`` is (a generated scene, searched with its onboarded model)."""
    random, onboarded = arm
    headers = {"Authorization": f"Bearer {calls.api_key}"} if calls.api_key else None
    timeout = aiohttp.ClientTimeout(total=600.0, connect=5.0)
    async with aiohttp.ClientSession(timeout=timeout, headers=headers) as http:
        target, image, bound = jobs[0]  # untimed: the scene's first free search loads it
        await search_target(http, calls, target, image, objects=objects, bound=bound, random=random)
        for k, (target, image, bound) in enumerate(jobs):
            if time.monotonic() > deadline:
                return False
            record = await search_target(
                http, calls, target, image, objects=objects, bound=bound, random=random,
                onboarded=onboarded,
            )  # fmt: skip
            checkpoint.add(record)
            if verbose or record.outcome == "error":
                say(
                    f"  [{k + 1}/{len(jobs)}] {record.scene} {record.variant:<8} #{record.index:<3}"
                    f" {record.band:<6} {record.outcome:<9} {record.renders} render(s) "
                    f"{record.wall_ms:6.0f} ms  {record.reason[:100]}"
                )
    return True


class _OwnArm:
    """The generated scenes onboarded one by one, each searched again with its own model."""

    def __init__(
        self,
        config: BenchConfig,
        ep: Endpoints,
        calls: StackCalls,
        checkpoint: Checkpoint,
        notes: list[str],
        deadline: float,
    ) -> None:
        self.config, self.ep, self.calls = config, ep, calls
        self.checkpoint, self.notes, self.deadline = checkpoint, notes, deadline

    def _note(self, text: str) -> None:
        self.notes.append(text)
        say(text)

    def run(self, scenes: Sequence[str], scene_dir: Path, work_root: Path) -> bool:
        """Onboard and search each of ``scenes``; False when the deadline stopped it."""
        onboard, why_not = onboarder(self.config.onboard or "none")
        if onboard is None:
            self._note(why_not)
            return True
        for scene_id in scenes:
            if time.monotonic() > self.deadline:
                return False
            jobs = _jobs(self.config, self.ep, scene_id, self.checkpoint.records, self.notes, True)
            if not jobs:
                continue
            say(f"onboarding {scene_id} ({self.config.onboard})")
            try:
                report = onboard(scene_dir / f"{scene_id}.yaml", work_root / scene_id)
            except (ImportError, OSError, RuntimeError, ValueError) as exc:
                self._note(f"onboarding {scene_id} failed: {type(exc).__name__}: {exc}")
                continue
            model = wait_for_model(self.ep, scene_id, jobs[0][0].png)
            if model.get("scene") != scene_id:
                self._note(f"{scene_id}: the detector does not serve its own model")
                continue
            self._note(f"{scene_id} onboarded: {onboarding_summary(report)}")
            scene = self.ep.scene_of(scene_id)
            finished = asyncio.run(
                _search_jobs(
                    self.calls, jobs, scene_objects(scene.spec, scene.assets), (True, True),
                    self.checkpoint, self.deadline, self.config.verbose,
                )
            )  # fmt: skip
            if not finished:
                return False
        return True


def _run(config: BenchConfig, root: Path) -> int:
    started = time.perf_counter()
    deadline = time.monotonic() + 60.0 * config.chunk_minutes if config.chunk_minutes else math.inf
    scene_dir = root / "scenes"
    scene_dir.mkdir(parents=True, exist_ok=True)
    random_ids = tuple(f"rand{config.seed}-{i}" for i in range(config.random_scenes))
    for i, scene_id in enumerate(random_ids):
        generate_scene(np.random.default_rng([config.seed, i]), scene_dir, scene_id)
    scenes = (*config.scenes, *random_ids)
    checkpoint = Checkpoint(config.out / CHECKPOINT, _fingerprint(config, scenes))
    if checkpoint.set_aside:
        say(f"a checkpoint of another run was set aside ({CHECKPOINT}.old)")
    notes = [*config.notes]
    if checkpoint.records:
        say(f"resuming: {len(checkpoint.records)} searches already in {checkpoint.path}")
        notes.append(
            f"resumed from a checkpoint of {len(checkpoint.records)} searches: the machine and "
            "duration are this last chunk's"
        )
    if random_ids:
        notes.append("random scenes are searched with the general detector (not onboarded)")
        if config.onboard != "none":
            notes.append(f"then onboarded ({config.onboard}) and searched with their own")
    complete = True
    with open_endpoints(config, spp=config.spp, width=config.width, scene_dirs=(scene_dir,)) as ep:
        machine = machine_info(services_info(ep, config.spp, config.width))
        machine["target_width"] = config.target_width or "scene's own (its camera's film)"
        if config.target_aspect is not None:
            machine["target_aspect"] = "{}:{}".format(*config.target_aspect)
        low, high = _fov_range(config)
        machine["target_fov"] = f"{low:g}-{high:g} times the scene camera's"
        machine["target_roll"] = f"within ±{_roll_limit(config):g}°"
        ep.warm(scenes)
        calls = StackCalls(
            ep.controller, ep.renderer, ep.detectors[0], ep.api_key, ep.service_token,
            config.max_iterations,
        )  # fmt: skip
        for scene_id in scenes:
            if time.monotonic() > deadline:
                complete = False
                break
            jobs = _jobs(config, ep, scene_id, checkpoint.records, notes)
            if not jobs:
                continue
            scene = ep.scene_of(scene_id)
            objects = scene_objects(scene.spec, scene.assets)
            finished = asyncio.run(
                _search_jobs(
                    calls, jobs, objects, (scene_id in random_ids, False), checkpoint, deadline,
                    config.verbose,
                )
            )  # fmt: skip
            if not finished:
                complete = False
                break
        if complete and random_ids and config.onboard != "none":
            own = _OwnArm(config, ep, calls, checkpoint, notes, deadline)
            complete = own.run(random_ids, scene_dir, root / "onboard")
    records = [r for r in checkpoint.records.values() if r.scene in scenes]
    say("")
    say(free_tables(records))
    say(f"\n{wrong_line(records)}")
    for line in goal_checks_by_detector(records):
        say(f"  {line}")
    say(time_line(records))
    skipped = sum(note.startswith("skipped ") for note in notes)  # scenes with no targets
    onboarded = len(random_ids) if config.onboard != "none" else 0
    planned = (len(scenes) + onboarded - skipped) * config.n * len(config.variants)
    if not complete:
        notes.append(
            f"partial: {len(records)} of {planned} searches; run the same command to resume"
        )
        say(notes[-1])
    report: dict[str, Any] = {
        "command": config.command,
        "machine": machine | load_at_end(),
        "duration_s": time.perf_counter() - started,
        "complete": complete,
        "planned": planned,
        "config": _fingerprint(config, scenes) | {"random_scenes": config.random_scenes},
        "notes": notes,
        "records": [r.model_dump(mode="json") for r in records],
    }
    write_report(config, "free.json", report)
    if complete:
        checkpoint.remove()
    return 1 if any(r.outcome == "error" for r in records) else 0


def run_free(config: BenchConfig) -> int:
    """The free-target bench (module docstring); the exit status (1 if any search errored)."""
    if config.url is not None:
        raise ValueError("--free starts its own stack (photo and changed need it): leave out --url")
    config = replace(config, onboard=config.onboard or "none")
    if config.scenes_out is not None:
        return _run(config, config.scenes_out)
    with tempfile.TemporaryDirectory(prefix="cosmos-free-scenes-") as tmp:
        return _run(config, Path(tmp))
