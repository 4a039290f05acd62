"""Whether a free bench miss had the boxes it needed: the recorded detections against the
renderer's true boxes, and the box solve's estimate per count of right boxes.

Run: ``.venv/bin/python -m benchmarks.free_truth out/bench-free/free.json [more.json …]
[--detector general] [--all-variants] [--all-intrinsics]``

Each run's targets are drawn again as it drew them (:func:`~cosmos.bench.free_targets.draw.
draw_targets`, its seed, count, film, fov range and roll limit; its generated scenes made again
from its seed), in this process, for their ground truth. A recorded detection is *right* when
its box overlaps the visible box of an object at least 60 % visible (the objects a target is
drawn to show) with IoU ≥ :data:`MIN_IOU` and its label names that object: its identity class
or name (a scene's own model) or its shape (the general model). Each record's detections are
solved again (:func:`benchmarks.free_replay.replayed`, this code). It prints, per detector and
per number of right detections (≤2, 3, ≥4), the targets, how many of them had a box on no
such object, and the box estimates within 10 %/5° and 5 %/2°: a solve that misses with four
right boxes is the solve's to mend, one with two is the detector's. By default only the
goal's variants (clean, JPEG, noise) with the fov given are counted.

The draw renders each target once more (16 samples a pixel): about a second a target.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from benchmarks.free_replay import GOAL_VARIANTS, LIMITS, _records, replayed, run_catalog
from cosmos.bench.free_bench.records import FreeRecord
from cosmos.bench.free_targets.draw import (
    FOV_RANGE,
    ROLL_LIMIT_DEG,
    FreeTarget,
    draw_targets,
    target_film,
)
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from services.common.geometry.scene import LoadedScene
from services.common.scene_models import object_classes
from services.optimizer.free_pose import SceneObjectCache
from services.renderer.settings import RendererSettings
from training.metrics import box_iou

MIN_IOU: Final = 0.5


def right_and_stray(record: FreeRecord, target: FreeTarget, scene: LoadedScene) -> tuple[int, int]:
    """How many of ``record``'s detections are right (module docstring), and how many lie on
    no object at least 60 % visible."""
    shown = [o for o in target.annotations.objects if o.name in target.usable and o.box]
    if not record.target_detections:
        return 0, 0
    if not shown:
        return 0, len(record.target_detections)
    classes = {name: c.label for c in object_classes(scene.spec) for name in c.objects}
    overlaps = box_iou(
        np.array([d.box for d in record.target_detections]), np.array([o.box for o in shown])
    )
    right = stray = 0
    for d, row in zip(record.target_detections, overlaps, strict=True):
        best = shown[int(np.argmax(row))]
        if row.max() < MIN_IOU:
            stray += 1
            continue
        right += d.label in {best.name, best.shape, classes.get(best.name, best.name)}
    return right, stray


def _targets(
    renderer: LocalRenderer, scene: LoadedScene, config: dict[str, Any]
) -> dict[int, FreeTarget]:
    aspect = config.get("target_aspect")
    width, height = target_film(
        config.get("target_width"),
        (int(aspect[0]), int(aspect[1])) if aspect else None,
        scene.spec.camera.width,
    )
    low, high = config.get("fov_range") or FOV_RANGE
    drawn = draw_targets(
        renderer,
        scene,
        scene_shapes(scene),
        int(config["n"]),
        int(config["seed"]),
        width=width,
        height=height,
        fov_range=(float(low), float(high)),
        roll_limit=float(config.get("roll_limit", ROLL_LIMIT_DEG)),
    )
    return {t.index: t for t in drawn}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.free_truth", description=__doc__)
    parser.add_argument("reports", nargs="+", type=Path, help="free.json of cosmos bench --free")
    parser.add_argument("--detector", choices=("own", "general"), help="only this detector")
    parser.add_argument("--all-variants", action="store_true")
    parser.add_argument("--all-intrinsics", action="store_true", help="the fov not given too")
    args = parser.parse_args(argv)
    variants = None if args.all_variants else list(GOAL_VARIANTS)
    rows: dict[tuple[str, str], list[tuple[bool, bool, bool]]] = defaultdict(list)
    settings = RendererSettings()
    for path in args.reports:
        records, config = _records(path, variants)
        records = [
            r
            for r in records
            if (args.all_intrinsics or r.intrinsics_given)
            and (args.detector is None or r.detector == args.detector)
        ]
        with tempfile.TemporaryDirectory(prefix="cosmos-truth-") as tmp:
            catalog = run_catalog(config, Path(tmp), settings)
            cache = SceneObjectCache()
            drawn: dict[str, dict[int, FreeTarget]] = {}
            with LocalRenderer(catalog, settings) as renderer:
                for record in records:
                    scene = catalog.get(record.scene)
                    if record.scene not in drawn:
                        drawn[record.scene] = _targets(renderer, scene, config)
                    target = drawn[record.scene].get(record.index)
                    if target is None:
                        continue
                    right, stray = right_and_stray(record, target, scene)
                    error, _ = replayed(record, catalog, cache)
                    group = "≤2" if right <= 2 else "3" if right == 3 else "≥4"
                    loose, tight = (error.within(*lim) for lim in LIMITS)
                    rows[(record.detector, group)].append((stray > 0, loose, tight))
    print("right detections: targets · with a stray box · box estimate within 10 %/5° · 5 %/2°")
    for (detector, group), row in sorted(rows.items()):
        counts = [sum(r[k] for r in row) for k in range(3)]
        print(f"{detector:8s} {group:5s} {len(row):4d} · {counts[0]:4d} · {counts[1]:4d} · "
              f"{counts[2]:4d}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
