"""The target's side of ``POST /refine-pose``: what keeping it between a search's renders saves.

Run: ``.venv/bin/python -m benchmarks.target_maps [--views 4] [--repeat 3]``

Free views of the demo scene (drawn from ``--seed``), each as a search refines them: the box
pose's render with its depth on a film of 320 x 240 (the search's default view width) and the
target as a 320 x 240 PNG, and as a 4000 x 3000 JPEG (a drone's photo of the same view) whose
render is 640 x 480. For each it times, alternating so that both see the same load:

* ``refine_pose`` with nothing kept (the first render of a search), and again with the
  target's grey image and distance maps kept (every later render);
* the full-resolution distance-map level itself, as ``target_level`` makes it now and as
  ``exact_distance`` and ``np.gradient`` made it before (the same maps bit for bit).

It prints the medians (ms), the differences and the ratios, each measured in this one run.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.free import FreePoseRequest
from services.common.contracts.optimize import ImageDetections
from services.common.contracts.refine import RefinePoseRequest
from services.common.geometry.free_camera import FreeCamera
from services.controller.free_match import scaled_camera
from services.optimizer.free import scene_objects
from services.optimizer.free.dense import LEVELS
from services.optimizer.free.edges import (
    ORIENTATION_BINS,
    Level,
    exact_distance,
    gray,
    image_edges,
    target_level,
)
from services.optimizer.free.target_maps import TargetMapCache
from services.optimizer.free_pose import SceneObjectCache, free_pose
from services.optimizer.refine_pose import ImageLimits, refine_pose
from services.renderer.engine import RenderEngine
from services.renderer.view import resolve_free_camera

LIMITS: Final = ImageLimits(4096 * 4096, 16_384)
FILMS: Final = (((320, 240), (320, 240), ".png"), ((4000, 3000), (640, 480), ".jpg"))
"""(target size, render film, target format)."""


def reference_level(image: NDArray[np.uint8], scale: int, sigma: float, cap: float) -> Level:
    """A level as ``target_level`` made it before: ``exact_distance`` over the whole map in
    float64, then ``np.gradient`` and a copy to float32 (the same downsampling)."""
    height, width = image.shape
    small = image
    if scale > 1:
        size = (max(width // scale, 8), max(height // scale, 8))
        small = np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    edges, bins = image_edges(small)
    distance = np.empty((ORIENTATION_BINS, *small.shape), dtype=np.float32)
    for b in range(ORIENTATION_BINS):
        near = (bins == b) | (bins == (b + 1) % ORIENTATION_BINS)
        near |= bins == (b - 1) % ORIENTATION_BINS
        free = np.where(edges & near, 0, 255).astype(np.uint8)
        raw = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        distance[b] = np.minimum(exact_distance(raw), cap)
    grad_y, grad_x = np.gradient(distance, axis=(1, 2))
    return Level(scale, sigma, cap, distance, grad_x.astype(np.float32), grad_y.astype(np.float32))


def _views(n: int, seed: int) -> list[FreeCamera]:
    """``n`` cameras 6-10 units from the centre, 25-80° up, looking near it, rolled ±20°."""
    rng = np.random.default_rng(seed)
    cameras = []
    for _ in range(n):
        distance, up = rng.uniform(6.0, 10.0), math.radians(rng.uniform(25.0, 80.0))
        around = rng.uniform(0.0, 2.0 * math.pi)
        position = (
            distance * math.cos(up) * math.cos(around),
            distance * math.cos(up) * math.sin(around),
            distance * math.sin(up),
        )
        look = (*rng.uniform(-0.5, 0.5, 2), 0.0)
        cameras.append(
            FreeCamera(
                position=position,
                look_at=look,
                roll_deg=float(rng.uniform(-20.0, 20.0)),
                fov_deg=float(rng.uniform(40.0, 60.0)),
            )
        )
    return cameras


def _encoded(rgb: NDArray[np.uint8], size: tuple[int, int], suffix: str) -> bytes:
    image = (
        rgb if rgb.shape[1::-1] == size else cv2.resize(rgb, size, interpolation=cv2.INTER_CUBIC)
    )
    ok, data = cv2.imencode(suffix, np.ascontiguousarray(image[..., ::-1]))
    assert ok
    return data.tobytes()


def _ms(call: Callable[[], object]) -> float:
    started = time.perf_counter()
    call()
    return (time.perf_counter() - started) * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    scene = catalog.get("demo")
    labels = scene_objects(scene.spec, scene.assets).labels
    objects = SceneObjectCache()
    timings: dict[str, list[float]] = {}

    def add(name: str, ms: float) -> None:
        timings.setdefault(name, []).append(ms)

    engine = RenderEngine("auto")
    engine.start()
    try:
        for truth in _views(args.views, args.seed):
            view = resolve_free_camera(scene, truth, 640, 480)
            image = engine.render(scene, view, 640, 480, 16, 1).rgb
            found = engine.annotate(
                scene, resolve_free_camera(scene, truth, 320, 240), 320, 240, None
            )
            boxes = [
                (labels[i], i, o.box)
                for i, o in enumerate(found.objects)
                if o.box is not None and o.visible_fraction >= 0.6
            ]
            for size, film, suffix in FILMS:
                k = size[0] / 320
                target = ImageDetections.model_validate(
                    {
                        "image_size": list(size),
                        "detections": [
                            {
                                "label": name,
                                "class_id": i,
                                "confidence": 0.9,
                                "box": [v * k for v in box],
                            }
                            for name, i, box in boxes
                        ],
                    }
                )
                ask = FreePoseRequest(
                    scene="demo", target=target, intrinsics={"fov_deg": truth.fov_deg}
                )
                pose = free_pose(ask, catalog, objects).pose
                if pose is None:
                    continue
                data = _encoded(image, size, suffix)
                at = resolve_free_camera(scene, scaled_camera(pose, film[0] / size[0]), *film)
                render = replace(
                    engine.depth(scene, at, *film), rgb=engine.render(scene, at, *film, 8, 0).rgb
                ).npz()
                request = RefinePoseRequest(scene="demo", pose=pose, fit_focal=False)
                fine = gray(np.asarray(cv2.resize(image, film, interpolation=cv2.INTER_AREA)))
                tag, level = f"{size[0]}x{size[1]}", f"{film[0]}x{film[1]} level"
                for _ in range(args.repeat):
                    kept = TargetMapCache()
                    refine = partial(refine_pose, request, data, render, catalog, objects)
                    add(f"{tag} first", _ms(partial(refine, LIMITS, kept)))
                    add(f"{tag} later", _ms(partial(refine, LIMITS, kept)))
                    add(f"{level} before", _ms(partial(reference_level, fine, *LEVELS[-1])))
                    add(f"{level} now", _ms(partial(target_level, fine, *LEVELS[-1])))
    finally:
        engine.close()
    medians = {name: statistics.median(ms) for name, ms in timings.items()}
    print(f"{'ms per call (median)':34s} {'n':>4s} {'ms':>8s}")
    for name, ms in timings.items():
        print(f"{name:34s} {len(ms):4d} {medians[name]:8.1f}")
    print()
    for size, _, _ in FILMS:
        tag = f"{size[0]}x{size[1]}"
        first, later = medians[f"{tag} first"], medians[f"{tag} later"]
        saved = f"{first - later:.1f} ms less ({later / first:.2f} x)"
        print(f"refine_pose, target {tag}: a later render of the search {saved}")
    for _, film, _ in FILMS:
        tag = f"{film[0]}x{film[1]}"
        before, now = medians[f"{tag} level before"], medians[f"{tag} level now"]
        print(f"full-resolution level at {tag}: {before:.1f} → {now:.1f} ms ({now / before:.2f} x)")


if __name__ == "__main__":
    main()
