"""Box solve speed: ms per ``solve_free_pose`` with one edge fit per distinct start, against a
fit for every start, on the same free targets.

Run: ``.venv/bin/python -m benchmarks.free_solve [--seed 1] [--n 8] [--random-scenes 2]
[--repeat 3]``

Targets: the free bench's draw (:func:`cosmos.bench.free_targets.draw.draw_targets`) on demo,
garden and ``--random-scenes`` generated scenes. Their detections are the renderer's boxes with
the detector's edge noise (:func:`cosmos.bench.free_targets.solver.target_detections`), labelled
twice: as the scene's own detector names the objects (``own``) and by shape, as the general model
does (``general``). Each is solved with the intrinsics given and without, under the module's
constants (``shared``) and with :data:`~services.optimizer.free.hypothesis_fits.SAME_START_POSITION`
and ``SAME_START_DEG`` below zero, which fits every start (``every``), alternating so that both
see the same load. It prints per scene and labels the median ms per solve, the median ratio of
the best of ``--repeat`` runs, and how many answers differ (status, alternatives, or pose and
fov by more than 1e-4 units or degrees).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Final

import numpy as np

from cosmos.bench.free_targets.draw import draw_targets
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solver import target_detections
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.contracts.detect import Detection
from services.optimizer.free import (
    FreePoseAnswer,
    Intrinsics,
    SceneObjects,
    hypothesis_fits,
    scene_objects,
    solve_free_pose,
)
from services.renderer.settings import RendererSettings

SAME: Final = 1e-4
"""Answers whose poses and fov agree to this (units, degrees) count as the same."""
Case = tuple[str, str, list[Detection], int, int, Intrinsics | None]


@contextmanager
def _every_start() -> Iterator[None]:
    """Fit every start: no two starts count as the same."""
    saved = hypothesis_fits.SAME_START_POSITION, hypothesis_fits.SAME_START_DEG
    hypothesis_fits.SAME_START_POSITION, hypothesis_fits.SAME_START_DEG = -1.0, -1.0  # type: ignore[misc]
    try:
        yield
    finally:
        hypothesis_fits.SAME_START_POSITION, hypothesis_fits.SAME_START_DEG = saved  # type: ignore[misc]


def _general(detections: list[Detection], objects: SceneObjects) -> list[Detection]:
    """The detections labelled by their object's shape, as the general model labels them."""
    shapes = dict(zip(objects.labels, objects.shapes, strict=True))
    names = sorted(set(objects.shapes))
    return [
        d.model_copy(update={"label": shapes[d.label], "class_id": names.index(shapes[d.label])})
        for d in detections
    ]


def _cases(seed: int, n: int, random_scenes: int) -> tuple[list[Case], dict[str, SceneObjects]]:
    settings = RendererSettings()
    cases: list[Case] = []
    objects_of: dict[str, SceneObjects] = {}
    with tempfile.TemporaryDirectory(prefix="cosmos-solve-bench-") as tmp:
        ids = ["demo", "garden"]
        for i in range(random_scenes):
            ids.append(f"rand{seed}-{i}")
            generate_scene(np.random.default_rng([seed, i]), Path(tmp), ids[-1])
        catalog = SceneCatalog([*settings.scene_directories(), Path(tmp)])
        with LocalRenderer(catalog, settings) as renderer:
            for scene_id in ids:
                scene = catalog.get(scene_id)
                objects = objects_of[scene_id] = scene_objects(scene.spec, scene.assets)
                for target in draw_targets(renderer, scene, scene_shapes(scene), n, seed):
                    rng = np.random.default_rng([seed, target.index, 2])
                    own = target_detections(target, objects, rng)
                    film = target.annotations.camera
                    k = Intrinsics(film.fx, film.fy, film.cx, film.cy)
                    for labels, detections in (("own", own), ("general", _general(own, objects))):
                        for given in (k, None):
                            cases.append(
                                (scene_id, labels, detections, film.width, film.height, given)
                            )
    return cases, objects_of


def _key(answer: FreePoseAnswer) -> tuple[str, int, np.ndarray | None]:
    pose = answer.pose
    if pose is None:
        return answer.status, len(answer.alternatives), None
    values = [*pose.position, *pose.quaternion_wxyz, pose.intrinsics.fov_deg]
    return answer.status, len(answer.alternatives), np.array(values)


def _same(a: tuple[str, int, np.ndarray | None], b: tuple[str, int, np.ndarray | None]) -> bool:
    if a[:2] != b[:2] or (a[2] is None) != (b[2] is None):
        return False
    return a[2] is None or b[2] is None or bool(np.abs(a[2] - b[2]).max() <= SAME)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--n", type=int, default=8, help="targets drawn per scene")
    parser.add_argument("--random-scenes", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    cases, objects_of = _cases(args.seed, args.n, args.random_scenes)
    groups: dict[tuple[str, str], dict[str, list[float]]] = {}
    for scene_id, labels, detections, width, height, k in cases:
        objects = objects_of[scene_id]
        best = {"shared": math.inf, "every": math.inf}
        keys = {}
        for _ in range(args.repeat):
            for name in ("shared", "every"):
                started = time.perf_counter()
                if name == "every":
                    with _every_start():
                        answer = solve_free_pose(objects, detections, width, height, k)
                else:
                    answer = solve_free_pose(objects, detections, width, height, k)
                best[name] = min(best[name], (time.perf_counter() - started) * 1000.0)
                keys[name] = _key(answer)
        group = groups.setdefault((scene_id, labels), {"shared": [], "every": [], "differ": []})
        group["shared"].append(best["shared"])
        group["every"].append(best["every"])
        group["differ"].append(0.0 if _same(keys["shared"], keys["every"]) else 1.0)
    print(
        f"{'scene':10s} {'labels':8s} {'solves':>6s} {'shared ms':>10s} {'every ms':>9s} "
        f"{'ratio':>6s} {'differ':>6s}"
    )
    for (scene_id, labels), group in groups.items():
        ratio = np.median(np.array(group["shared"]) / np.array(group["every"]))
        print(
            f"{scene_id:10s} {labels:8s} {len(group['shared']):6d} "
            f"{np.median(group['shared']):10.1f} {np.median(group['every']):9.1f} "
            f"{ratio:6.2f} {int(sum(group['differ'])):6d}"
        )


if __name__ == "__main__":
    main()
