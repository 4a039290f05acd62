"""Render throughput at 320x240: prints renders/s cold and warm, spp 4 and 16, in place vs rebuilt.

Run: ``.venv/bin/python -m benchmarks.render [--renders 40] [--scene demo]``

* cold: the first render of a fresh process (scene load, kernel compile or disk-cache lookup),
  measured in a child process per spp;
* warm: renders per second at random poses once the scene is loaded;
* rebuild: the same renders, but loading the scene anew for each one (what the engine avoids by
  moving the camera through ``mi.traverse``); the ratio is measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from typing import Any

import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.geometry.camera import mitsuba_to_world
from services.common.geometry.pose import Pose
from services.renderer.engine import RenderEngine
from services.renderer.scene_builder import build_scene

WIDTH, HEIGHT = 320, 240


def _poses(count: int, seed: int) -> list[Pose]:
    rng = np.random.default_rng(seed)
    return [
        Pose(theta_deg=float(t), phi_deg=float(p))
        for t, p in zip(rng.uniform(0, 85, count), rng.uniform(0, 360, count), strict=True)
    ]


def cold_probe(scene_id: str, spp: int) -> float:
    """Seconds from a fresh engine to the first finished render (run in a child process)."""
    started = time.perf_counter()
    engine = RenderEngine("auto")
    engine.start()
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get(scene_id)
    engine.render(scene, Pose(theta_deg=40, phi_deg=120), WIDTH, HEIGHT, spp)
    elapsed = time.perf_counter() - started
    engine.close()
    return elapsed


def _rebuild_and_render(engine: RenderEngine, scene: Any, pose: Pose, spp: int, seed: int) -> None:
    mi = engine._mi  # benchmark-only: the worker's Mitsuba module
    loaded = mi.load_dict(build_scene(mi, scene, WIDTH, HEIGHT), optimize=False)
    params = mi.traverse(loaded)
    params["camera.to_world"] = mi.ScalarTransform4f(
        mitsuba_to_world(pose, scene.spec.camera.radius).tolist()
    )
    params.update()
    camera = next(s for s in loaded.sensors() if s.id() == "camera")
    np.asarray(mi.render(loaded, sensor=camera, spp=spp, seed=seed))


def bench_scene(engine: RenderEngine, scene_id: str, renders: int) -> dict[str, Any]:
    """Cold, warm and rebuild figures of one scene at spp 4 and 16."""
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get(scene_id)
    poses = _poses(renders, seed=1)
    figures: dict[str, Any] = {}
    for spp in (4, 16):
        probe = subprocess.run(
            [
                sys.executable,
                "-m",
                "benchmarks.render",
                "--scene",
                scene_id,
                "--cold-probe",
                str(spp),
            ],
            capture_output=True,
            text=True,
            check=True,
        )
        cold_s = float(probe.stdout.strip().splitlines()[-1])
        engine.render(scene, poses[0], WIDTH, HEIGHT, spp)  # warm this spp up
        started = time.perf_counter()
        for i, pose in enumerate(poses):
            engine.render(scene, pose, WIDTH, HEIGHT, spp, seed=i)
        warm_rps = len(poses) / (time.perf_counter() - started)
        started = time.perf_counter()
        for i, pose in enumerate(poses):
            engine.call(_rebuild_and_render, engine, scene, pose, spp, i)
        rebuild_rps = len(poses) / (time.perf_counter() - started)
        figures[f"spp{spp}"] = {
            "cold_first_render_s": cold_s,
            "warm_renders_per_s": warm_rps,
            "rebuild_renders_per_s": rebuild_rps,
            "update_in_place_over_rebuild": warm_rps / rebuild_rps,
        }
    started = time.perf_counter()
    for pose in poses:
        engine.annotate(scene, pose, WIDTH, HEIGHT, None)
    figures["annotations_per_s"] = len(poses) / (time.perf_counter() - started)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scene", action="append", help="scene id (repeatable; default: all built-in)"
    )
    parser.add_argument("--renders", type=int, default=40, help="random poses per row")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    parser.add_argument("--cold-probe", type=int, metavar="SPP", help=argparse.SUPPRESS)
    args = parser.parse_args()
    scenes = args.scene or SceneCatalog([BUILTIN_SCENES_DIR]).ids()
    if args.cold_probe is not None:
        print(cold_probe(scenes[0], args.cold_probe))
        return

    engine = RenderEngine("auto")
    engine.start()
    report: dict[str, Any] = {"variant": engine.variant, "size": [WIDTH, HEIGHT], "scenes": {}}
    for scene_id in scenes:
        report["scenes"][scene_id] = bench_scene(engine, scene_id, args.renders)
    engine.close()

    print(
        f"render benchmark: {WIDTH}x{HEIGHT}, variant {report['variant']}, "
        f"{args.renders} random poses per row (cold: first render of a fresh process)"
    )
    print(
        f"{'scene':>8} {'spp':>4} {'cold':>9} {'warm renders/s':>15} {'rebuild renders/s':>18} "
        f"{'in-place / rebuild':>19} {'annotations/s':>14}"
    )
    for scene_id, figures in report["scenes"].items():
        for spp in (4, 16):
            row = figures[f"spp{spp}"]
            print(
                f"{scene_id:>8} {spp:>4} {row['cold_first_render_s'] * 1000:>6.0f} ms "
                f"{row['warm_renders_per_s']:>15.1f} {row['rebuild_renders_per_s']:>18.1f} "
                f"{row['update_in_place_over_rebuild']:>18.2f}x "
                f"{figures['annotations_per_s']:>14.1f}"
            )
    if args.json:
        print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
