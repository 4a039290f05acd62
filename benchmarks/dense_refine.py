"""Dense refinement speed: prints ms per refine_dense call (focal fitted, K given), now vs before.

Run: ``.venv/bin/python -m benchmarks.dense_refine [--pairs DIR] [--n 6] [--repeat 3]``

Pairs: free targets of the demo scene and one generated scene (``cosmos.bench.free_targets``'
draw, seed 1), each with the box solver's pose and the render (RGB and depth) at it, as a free
search's dense stage gets them. They are drawn and rendered once (in this process) and kept in
``--pairs`` (one ``.npz`` each); later runs only time the refinement.

Each pair is refined with the focal length fitted and with the intrinsics given, under the
module's constants ("now") and under :data:`REFERENCE` (every point at every level and
``least_squares``' default ``xtol``, as before the speed-up), alternating so that both see the
same load. It prints per setting the median and p95 ms per call, the median speed-up and how
far the two settings' fits land from the true camera (position in radii, rotation in °).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from cosmos.bench.free_targets.dense import render_at
from cosmos.bench.free_targets.draw import draw_targets
from cosmos.bench.free_targets.metrics import rotation_angle_deg
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solver import solve_target
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.depth_archive import DepthImage
from services.common.geometry.camera import PinholeCamera
from services.optimizer.free import dense as dense_module
from services.optimizer.free import scene_objects
from services.optimizer.free.edges import outline
from services.renderer.settings import RendererSettings

REFERENCE: Final[dict[str, Any]] = {
    "LEVEL_POINTS": (None, None, None),
    "X_TOLERANCE": 1e-8,
    "FINE_START_SHARE": math.inf,
}
"""The module constants as they were before the speed-ups: every point at every level,
``least_squares``' default ``xtol``, and every level for every start (the numpy projection
stays: it changes no result)."""
SEED: Final = 1


@contextmanager
def _constants(values: dict[str, Any]) -> Iterator[None]:
    saved = {name: getattr(dense_module, name) for name in values}
    for name, value in values.items():
        setattr(dense_module, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(dense_module, name, value)


def _capture(folder: Path, n: int) -> None:
    """Draw, solve and render the pairs into ``folder`` (module docstring)."""
    folder.mkdir(parents=True, exist_ok=True)
    settings = RendererSettings()
    with tempfile.TemporaryDirectory(prefix="cosmos-dense-bench-") as tmp:
        generate_scene(np.random.default_rng([SEED, 0]), Path(tmp), "rand-bench")
        catalog = SceneCatalog([*settings.scene_directories(), Path(tmp)])
        with LocalRenderer(catalog, settings) as renderer:
            for scene_id in ("demo", "rand-bench"):
                scene = catalog.get(scene_id)
                shapes = scene_shapes(scene)
                objects = scene_objects(scene.spec, scene.assets)
                for target in draw_targets(renderer, scene, shapes, n, SEED):
                    rng = np.random.default_rng([SEED, target.index, 2])
                    answer = solve_target(target, objects, rng)
                    if answer.pose is None:
                        continue
                    rendered = render_at(renderer, target, answer.pose.free_camera(), 16)
                    if rendered is None:
                        continue
                    save_pair(
                        folder / f"{scene_id}-{target.index:02d}.npz",
                        target.png,
                        rendered,
                        target.annotations.camera,
                        scene.spec.camera.radius,
                    )


def save_pair(
    path: Path,
    image: bytes,
    rendered: tuple[NDArray[np.uint8], DepthImage, PinholeCamera],
    truth: PinholeCamera,
    radius: float,
    **extra: object,
) -> None:
    """One refinement case: the target ``image`` (grey), the render at the start pose (colours,
    depth, object ids, outline shading, camera), the true camera, the scene radius and
    ``extra`` scalars; read back by :func:`load_pair`."""
    rgb, geometry, camera = rendered
    gray = cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_GRAYSCALE)
    if gray is None or geometry.shading is None:
        raise ValueError("a target that does not decode, or a render without outline shading")
    np.savez_compressed(
        path,
        target=gray,
        rgb=rgb,
        depth=geometry.depth,
        objects=geometry.objects,
        shading=geometry.shading,
        camera=json.dumps(camera.model_dump(mode="json")),
        truth=json.dumps(truth.model_dump(mode="json")),
        radius=radius,
        **extra,  # type: ignore[arg-type]
    )


def load_pair(path: Path) -> dict[str, Any]:
    """A :func:`save_pair` case, its cameras parsed and the render's outline (``near``) made."""
    with np.load(path) as data:
        pair: dict[str, Any] = {name: data[name] for name in data.files}
    pair["near"] = (
        outline(pair["depth"], pair["objects"], pair["shading"]) if "shading" in pair else None
    )
    pair["camera"] = PinholeCamera.model_validate(json.loads(str(pair["camera"])))
    pair["truth"] = PinholeCamera.model_validate(json.loads(str(pair["truth"])))
    pair["radius"] = float(pair["radius"])
    return pair


def _run(pair: dict[str, Any], fit_focal: bool) -> tuple[float, float, float]:
    """One refinement: ms, position error (radii), rotation error (°)."""
    started = time.perf_counter()
    fit = dense_module.refine_dense(
        pair["target"],
        pair["rgb"],
        pair["depth"],
        pair["camera"],
        fit_focal=fit_focal,
        near=pair["near"],
    )
    ms = (time.perf_counter() - started) * 1000.0
    truth: PinholeCamera = pair["truth"]
    moved = float(np.linalg.norm(fit.position - np.asarray(truth.position))) / pair["radius"]
    turned = rotation_angle_deg(fit.rotation, np.asarray(truth.rotation))
    return ms, moved, turned


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, default=Path.home() / ".cache/cosmos/dense-pairs")
    parser.add_argument("--n", type=int, default=6, help="targets drawn per scene (capture)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if not any(args.pairs.glob("*.npz")):
        _capture(args.pairs, args.n)
    pairs = [load_pair(p) for p in sorted(args.pairs.glob("*.npz"))]
    settings = {"now": {}, "reference": REFERENCE}
    for fit_focal in (True, False):
        ms: dict[str, list[float]] = {name: [] for name in settings}
        errors: dict[str, list[tuple[float, float]]] = {name: [] for name in settings}
        ratios = []
        for pair in pairs:
            best: dict[str, float] = {}
            for _ in range(args.repeat):
                for name, values in settings.items():
                    with _constants(values):
                        took, moved, turned = _run(pair, fit_focal)
                    ms[name].append(took)
                    best[name] = min(best.get(name, math.inf), took)
                    errors[name].append((moved, turned))
            ratios.append(best["reference"] / best["now"])
        label = "focal fitted" if fit_focal else "intrinsics given"
        for name in settings:
            moved_all, turned_all = np.array(errors[name]).T
            print(
                f"{label:16s} {name:9s}: median {np.median(ms[name]):6.0f} ms, p95 "
                f"{np.percentile(ms[name], 95):6.0f} ms; error median {np.median(moved_all):.4f} r "
                f"{np.median(turned_all):.2f}°, max {moved_all.max():.4f} r {turned_all.max():.2f}°"
            )
        print(f"{label:16s} speed-up: median {np.median(ratios):.2f}x over {len(pairs)} pairs")


if __name__ == "__main__":
    main()
