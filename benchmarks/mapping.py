"""Object mapping, paper (eq. 2–7) vs exact: prints ground-position error per scene and class.

The paper's method (eq. 2–7) against ours (exact back-projection).

Run: ``.venv/bin/python -m benchmarks.mapping [--every 2] [--scene demo --scene garden]``

For every ``--every``-th grid pose of each scene the render engine annotates the view with exact
ground truth; each object's visible box (the renderer's own silhouette box, standing in for a
perfect detector) is mapped to the ground from the known pose, and the position error is the
distance to the object's true footprint centre, in scene units. Rows: per scene and class, for
wholly visible objects (``visible_fraction ≥ 0.99``; boxes cut by the image border included) and,
separately, for partly hidden ones. Methods side by side: ``exact`` (ours), ``paper`` (eq. 2–7
with the stored fitted coefficients and reference height) and ``paper h=0`` (eq. 4 literally,
rays intersected with the ground plane itself).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import defaultdict

import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.optimizer.calibration import CalibrationStore, PaperCalibration
from services.optimizer.mapping import map_exact, map_paper
from services.optimizer.proxies import kind_of
from services.renderer.engine import RenderEngine

METHODS = ("exact", "paper", "paper h=0")


def _errors(
    engine: RenderEngine, scene_id: str, every: int, calibration: PaperCalibration
) -> tuple[dict[tuple[str, bool], dict[str, list[float]]], int]:
    """Position errors per (class, wholly visible) and method, and the number of views."""
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    scene = catalog.get(scene_id)
    grid = scene.spec.search.grid()
    camera = scene.spec.camera
    literal = dataclasses.replace(calibration, reference_height=0.0)
    errors: dict[tuple[str, bool], dict[str, list[float]]] = defaultdict(
        lambda: {m: [] for m in METHODS}
    )
    views = 0
    for flat in range(0, grid.size, every):
        index = grid.unflat(flat)
        pose = grid.pose(index)
        ann = engine.annotate(scene, pose, camera.width, camera.height, index)
        objects = [o for o in ann.objects if o.box is not None]
        if not objects:
            continue
        views += 1
        boxes = np.array([o.box for o in objects])
        truth = np.array([o.position[:2] for o in objects])
        kinds = [kind_of(o.shape) for o in objects]
        mapped = {
            "exact": map_exact(boxes, kinds, camera, pose.theta_deg, pose.phi_deg).position,
            "paper": map_paper(boxes, camera, pose.theta_deg, pose.phi_deg, calibration).position,
            "paper h=0": map_paper(boxes, camera, pose.theta_deg, pose.phi_deg, literal).position,
        }
        for method, positions in mapped.items():
            distance = np.linalg.norm(positions - truth, axis=1)
            for obj, error in zip(objects, distance, strict=True):
                key = (obj.shape, obj.visible_fraction >= 0.99)
                errors[key][method].append(float(error) if np.isfinite(error) else np.inf)
    return errors, views


def _cell(values: list[float]) -> str:
    v = np.asarray(values)
    failed = int(np.sum(~np.isfinite(v)))
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return f"{'—':>7} {'—':>7}"
    text = f"{np.median(finite):7.3f} {np.percentile(finite, 95):7.3f}"
    return text + (f" ({failed} failed)" if failed else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", help="scene id (default: demo and garden)")
    parser.add_argument("--every", type=int, default=2, help="use every n-th grid pose")
    args = parser.parse_args()
    scenes = args.scene or ["demo", "garden"]
    calibrations = CalibrationStore.load()
    engine = RenderEngine("auto")
    engine.start()
    started = time.perf_counter()
    total_views = 0
    print("object mapping: position error in scene units (median / p95) from renderer boxes")
    header = (
        f"{'':>7} {'':>9} {'':>8} {'':>5} "
        + " ".join(f"{m:>15}" for m in METHODS)
        + f"\n{'scene':>7} {'class':>9} {'visible':>8} {'n':>5} "
        + " ".join(f"{'median':>7} {'p95':>7}" for _ in METHODS)
    )
    try:
        for scene_id in scenes:
            scene = SceneCatalog([BUILTIN_SCENES_DIR]).get(scene_id)
            calibration = calibrations.find(scene.spec.camera)
            if calibration is None:
                print(f"{scene_id}: no paper calibration stored; run tools/fit_paper_mapping.py")
                continue
            errors, views = _errors(engine, scene_id, args.every, calibration)
            total_views += views
            print(f"\n{scene_id}: {views} views (every {args.every}. grid pose)")
            print(header)
            for whole in (True, False):
                rows = sorted(k for k in errors if k[1] is whole)
                pooled: dict[str, list[float]] = {m: [] for m in METHODS}
                for shape, _ in rows:
                    cells = errors[(shape, whole)]
                    for m in METHODS:
                        pooled[m].extend(cells[m])
                    print(
                        f"{scene_id:>7} {shape:>9} {'whole' if whole else 'partly':>8} "
                        f"{len(cells['exact']):>5} " + " ".join(_cell(cells[m]) for m in METHODS)
                    )
                if rows:
                    print(
                        f"{scene_id:>7} {'all':>9} {'whole' if whole else 'partly':>8} "
                        f"{len(pooled['exact']):>5} " + " ".join(_cell(pooled[m]) for m in METHODS)
                    )
    finally:
        engine.close()
    print(f"\n{total_views} views in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
