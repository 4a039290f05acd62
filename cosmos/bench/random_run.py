"""``cosmos bench --random-scenes N``: generated scenes, the general detector, then their own.

1. N scenes from :func:`cosmos.bench.scenes.generate_scene` (scene ``i`` from the seed
   ``(seed, i)``) go into ``<scenes-out>/scenes/``, a folder the local stack reads
   (``COSMOS_SCENES_DIR``).
2. The bench's targets (``--n`` per scene and variant, random starts) are searched with the
   general model: no scene has a model of its own yet.
3. Each scene is onboarded (``training.onboard.onboard_scene``; ``--onboard tiny`` for a CI-sized
   model, ``none`` to skip; skipped with a note when training cannot be imported). The detector
   picks the new model up without a restart; the bench asks ``POST /detect?scene=<id>`` until the
   answer's ``model.scene`` names the scene, and records which model served.
4. The same targets, from the same starts, are searched again with the scene's own model.

Report: ``random.json`` (records labelled by ``arm``: general / scene), and its section of
``docs/RESULTS.md`` (:mod:`cosmos.bench.random_report`, :mod:`cosmos.bench.results_md`).
"""

from __future__ import annotations

import importlib
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Final

import httpx
import numpy as np

from cosmos.bench.machine import machine_info
from cosmos.bench.random_report import GOALS, band_cells, band_table, goal_checks
from cosmos.bench.runner import BenchTarget, SearchRecord, run_searches, with_starts
from cosmos.bench.scenes import generate_scene, scene_summary
from cosmos.bench.session import (
    BenchConfig,
    Endpoints,
    load_at_end,
    open_endpoints,
    progress_printer,
    say,
    search_all,
    services_info,
    write_report,
)
from services.common.auth import bearer
from services.common.geometry.scene import load_scene

__all__ = [
    "MODEL_WAIT_S",
    "describe_model",
    "model_status",
    "onboarder",
    "onboarding_summary",
    "run_random",
    "served_model",
    "wait_for_model",
]

MODEL_WAIT_S: Final = 60.0
"""How long the detector has to pick up a newly onboarded model."""

Onboard = Callable[[Path, Path], Any]


def served_model(
    detector_url: str, scene: str, image: bytes, token: str | None = None
) -> dict[str, Any]:
    """The model ``POST /detect?scene=<scene>`` answers with (``name``, ``sha256``, ``scene``);
    ``token`` is the stack's service token."""
    response = httpx.post(
        f"{detector_url}/detect",
        params={"scene": scene},
        content=image,
        headers={"Content-Type": "image/png", **bearer(token)},
        timeout=60.0,
    )
    response.raise_for_status()
    model = response.json().get("model", {})
    return {k: model.get(k) for k in ("name", "sha256", "scene")}


def model_status(detector_url: str, scene: str, token: str | None = None) -> str:
    """What ``GET /models`` says of ``scene``'s own model (``serving``, ``refused: why``,
    ``none``), or why it cannot say; ``token`` is the stack's service token."""
    try:
        response = httpx.get(f"{detector_url}/models", timeout=30.0, headers=bearer(token))
        response.raise_for_status()
        states = response.json().get("scenes", [])
    except (httpx.HTTPError, ValueError) as exc:
        return f"GET /models failed ({exc})"
    for state in states:
        if state.get("scene") == scene:
            error = state.get("error")
            return str(state.get("state")) + (f": {error}" if error else "")
    return "not listed by GET /models"


def describe_model(model: dict[str, Any]) -> str:
    kind = f"the scene's own ({model['scene']})" if model.get("scene") else "general"
    return f"{kind}: {model.get('name')} (sha256 {str(model.get('sha256'))[:12]})"


def onboarder(preset: str) -> tuple[Onboard | None, str]:
    """A function onboarding one scene with ``preset``'s options, or why there is none."""
    try:  # torch may be missing: then only the general arm runs
        module = importlib.import_module("training.onboard")
    except ImportError as exc:
        return None, f"onboarding unavailable ({exc}); the general model only"
    options = module.OnboardOptions.tiny() if preset == "tiny" else module.OnboardOptions()

    def onboard(scene_path: Path, work_dir: Path) -> Any:
        return module.onboard_scene(scene_path, options, work_dir=work_dir)

    return onboard, ""


def onboarding_summary(report: Any) -> str:
    parts = []
    for field, fmt in (
        ("minutes", "{:.1f} min"),
        ("precision", "P {:.3f}"),
        ("recall", "R {:.3f}"),
    ):
        value = getattr(report, field, None)
        if isinstance(value, int | float):
            parts.append(fmt.format(value))
    map50 = getattr(report, "map50", None)
    if isinstance(map50, int | float):
        parts.append(f"mAP50 {map50:.3f}")
    return ", ".join(parts) or str(report)


def wait_for_model(endpoints: Endpoints, scene: str, image: bytes) -> dict[str, Any]:
    """Ask every detector until each serves ``scene``'s own model (or :data:`MODEL_WAIT_S`
    passes); what the first one served last."""
    deadline = time.monotonic() + MODEL_WAIT_S
    while True:
        models = [
            served_model(url, scene, image, endpoints.service_token) for url in endpoints.detectors
        ]
        if all(m.get("scene") == scene for m in models) or time.monotonic() > deadline:
            return models[0]
        time.sleep(1.0)


def _scene_arm(
    config: BenchConfig,
    endpoints: Endpoints,
    targets: Sequence[BenchTarget],
    scene_dir: Path,
    work_root: Path,
    onboard: Onboard,
    models: list[dict[str, Any]],
) -> list[SearchRecord]:
    """Onboard each scene, check its model serves, search its targets again with it."""
    ready = []
    for scene in config.scenes:
        say(f"onboarding {scene} ({config.onboard})")
        started = time.perf_counter()
        try:
            report = onboard(scene_dir / f"{scene}.yaml", work_root / scene)
        except (ImportError, OSError, RuntimeError, ValueError) as exc:
            # One scene's failed training must not cost the run its general arm's figures.
            failure = f"failed: {type(exc).__name__}: {exc}"
            say(f"  onboarding {scene} {failure}")
            models.append({"scene": scene, "arm": "scene", "served": "—", "onboarding": failure})
            if isinstance(exc, ImportError):  # torch missing: no other scene will do better
                break
            continue
        summary = onboarding_summary(report)
        say(f"  onboarded {scene} in {time.perf_counter() - started:.0f} s: {summary}")
        image = next(t.image for t in targets if t.scene == scene)
        model = wait_for_model(endpoints, scene, image)
        models.append(
            {"scene": scene, "arm": "scene", "served": describe_model(model), "onboarding": summary}
        )
        if model.get("scene") == scene:
            ready.append(scene)
        else:
            status = model_status(endpoints.detectors[0], scene, endpoints.service_token)
            models[-1]["served"] += f"; the scene's own model: {status}"
            say(f"  the detector does not serve {scene}'s own model ({status})")
    jobs = [
        (t, s)
        for t in with_starts(targets, config.starts)
        if t.scene in ready
        for s in config.strategies
    ]
    if not jobs:
        return []
    firsts = {t.scene: t for t in reversed(targets) if t.scene in ready}
    run_searches(  # untimed: the new model's first inference per scene
        endpoints.controller,
        [(t, s) for t in firsts.values() for s in config.strategies],
        max_iterations=config.max_iterations,
        arm="scene",
        api_key=endpoints.api_key,
    )
    say(f"{len(jobs)} searches with the scenes' own models")
    return run_searches(
        endpoints.controller,
        jobs,
        concurrency=config.concurrency,
        max_iterations=config.max_iterations,
        progress=progress_printer(len(jobs), config.verbose),
        arm="scene",
        api_key=endpoints.api_key,
    )


def _run(config: BenchConfig, root: Path) -> int:
    started = time.perf_counter()
    scene_dir = root / "scenes"
    ids = tuple(f"rand{config.seed}-{i}" for i in range(config.random_scenes))
    scenes = []
    for i, scene in enumerate(ids):
        path = generate_scene(np.random.default_rng([config.seed, i]), scene_dir, scene)
        scenes.append(scene_summary(load_scene(path)))
        say(f"generated {path}: {scenes[-1]['objects']} objects, {', '.join(scenes[-1]['kinds'])}")
    config = replace(config, scenes=ids)
    notes = list(config.notes)
    models: list[dict[str, Any]] = []
    with open_endpoints(config, spp=config.spp, width=config.width, scene_dirs=(scene_dir,)) as ep:
        machine = machine_info(services_info(ep, config.spp, config.width))
        targets, records = search_all(config, ep, config.variants, config.strategies)
        for scene in ids:
            image = next(t.image for t in targets if t.scene == scene)
            token = ep.service_token
            served = served_model(ep.detectors[0], scene, image, token) if ep.detectors else {}
            models.append({"scene": scene, "arm": "general", "served": describe_model(served)})
        onboard, why_not = (None, "onboarding skipped (--onboard none)")
        if config.onboard is not None and config.onboard != "none":
            onboard, why_not = onboarder(config.onboard)
        if onboard is None:
            notes.append(why_not)
            say(why_not)
        else:
            records += _scene_arm(config, ep, targets, scene_dir, root / "onboard", onboard, models)
    cells = band_cells(records)
    say("")
    say(band_table(cells))
    say(f"\ngoals: {GOALS}")
    for line in goal_checks(cells):
        say(f"  {line}")
    report: dict[str, Any] = {
        "command": config.command,
        "machine": machine | load_at_end(),
        "duration_s": time.perf_counter() - started,
        "config": {
            "random_scenes": config.random_scenes,
            "n": config.n,
            "seed": config.seed,
            "strategies": config.strategies,
            "variants": config.variants,
            "starts": config.starts,
            "onboard": config.onboard,
            "spp": config.spp,
            "width": config.width,
            "max_iterations": config.max_iterations,
        },
        "notes": notes,
        "scenes": scenes,
        "models": models,
        "records": [r.model_dump(mode="json") for r in records],
    }
    write_report(config, "random.json", report)
    return 1 if any(r.status == "error" for r in records) else 0


def run_random(config: BenchConfig) -> int:
    """The random-scene bench (module docstring); the exit status (1 if any search errored)."""
    if config.url is not None:
        raise ValueError("--random-scenes starts its own stack: leave out --url")
    config = replace(config, onboard=config.onboard or "default")
    if config.scenes_out is not None:
        return _run(config, config.scenes_out)
    with tempfile.TemporaryDirectory(prefix="cosmos-random-scenes-") as tmp:
        return _run(config, Path(tmp))
