"""How much a target's edges say about its focal length, per elevation band.

Run: ``.venv/bin/python -m benchmarks.focal_valley [--n 8] [--seeds 1,2] [--random-scenes 2]
[--scale 2 [--enlarge]]``

Without the photo's intrinsics, distance and focal length trade along a valley (a dolly zoom:
focal ``s f``, the camera moved back by ``(s - 1) z̃``, the edge points' median depth ``z̃``
kept in place). How steep its walls are decides whether any fit can find the focal length.

Targets: free targets (``cosmos.bench.free_targets``' draw) of the demo scene and of
``--random-scenes`` generated scenes per seed, their clean images. Each is rendered at its true
camera as a search renders a view (8 samples a pixel; the target had 16),
and its outline edge points (:func:`~services.optimizer.free.edges.edge_points_by_outline`) are
fitted to the target's edges with the focal length held at ``s`` times the truth, for each ``s``
of :data:`ZOOMS`, the pose fitted coarse to fine from the true pose dolly-zoomed by ``s`` (the
dense refinement's own ``_align``). The valley's rise at ``s`` is the full-resolution robust
cost there over its least along the valley.

Then the search's situation: the target is rendered at a camera :data:`OFF` along the valley
either way, and :func:`~services.optimizer.free.dense.refine_dense` fits the pose and the focal
length from that render; the fov errors of those fits are tallied.

It prints per elevation band the median rise at ``s`` = 0.9, 0.95, 1.05 and 1.1, and the share of
the free fits within 1 % and 2 % of the true fov.

``--scale S`` draws the target and the views on a film ``S`` times over: a photo that large.
With ``--enlarge`` the target keeps its own film and its grey is enlarged to the views'
(``cv2.INTER_CUBIC``), as the optimizer does for a small photo without its intrinsics
(``services.optimizer.refine_pose``), and the fits take their tolerances in its pixels
(:func:`~services.optimizer.free.dense.pyramid`).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from cosmos.bench.free_targets.dense import render_at
from cosmos.bench.free_targets.draw import BANDS, Band, FreeTarget, draw_targets
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.geometry.camera import PinholeCamera
from services.common.geometry.free_camera import FreeCamera
from services.optimizer.free import dense, level_fit
from services.optimizer.free.chamfer import ChamferProblem
from services.optimizer.free.edges import (
    EdgePoints,
    edge_points_by_outline,
    on_film,
    outline,
    target_level,
)
from services.optimizer.free.refine import Intrinsics
from services.renderer.settings import RendererSettings

ZOOMS: Final = (0.9, 0.95, 0.98, 1.0, 1.02, 1.05, 1.1)
SHOWN: Final = (0.9, 0.95, 1.05, 1.1)
OFF: Final = (0.97, 1.03)
"""The renders the free fits start from: this far along the valley from the truth."""
VIEW_SPP: Final = 8
TARGET_SPP: Final = 16


def _targets(
    renderer: LocalRenderer, catalog: SceneCatalog, ids: list[str], n: int, seed: int
) -> Iterator[FreeTarget]:
    for scene_id in ids:
        scene = catalog.get(scene_id)
        yield from draw_targets(renderer, scene, scene_shapes(scene), n, seed)


def _render(
    renderer: LocalRenderer, target: FreeTarget, camera: FreeCamera, scale: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, PinholeCamera]:
    """The render at ``camera`` on the target's film ``scale`` times over (as a search's view):
    RGB, depth, outline, pinhole."""
    rendered = render_at(renderer, target, camera, VIEW_SPP, scale=scale)
    if rendered is None:
        raise ValueError(f"the renderer refused a camera of {target.scene} #{target.index}")
    rgb, depth, pinhole = rendered
    shading = depth.shading
    if shading is None:
        shading = np.zeros(depth.objects.shape, np.uint8)
    return rgb, depth.depth, outline(depth.depth, depth.objects, shading), pinhole


def _target_image(renderer: LocalRenderer, target: FreeTarget, scale: int) -> bytes:
    """The target's clean image, drawn again on a film ``scale`` times over (16 samples a
    pixel, as drawn) when ``scale`` > 1."""
    if scale == 1:
        return target.png
    film = target.annotations.camera
    request = RenderRequest(
        scene=target.scene,
        camera=target.camera,
        width=film.width * scale,
        height=film.height * scale,
        spp=TARGET_SPP,
        seed=target.index,
    )
    return renderer.render_png(request)


def _decoded(png: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the renderer's PNG does not decode")
    return np.asarray(bgr)


def _dolly(target: FreeTarget, zoom: float) -> FreeCamera:
    """The target's camera moved along its line of sight to ``zoom`` times its distance from
    the point it looks at, its fov narrowed to keep that point's neighbourhood in place."""
    camera = target.camera
    look = np.asarray(target.drawn.look_at)
    position = look + (np.asarray(camera.position) - look) * zoom
    assert camera.fov_deg is not None
    fov = math.degrees(2.0 * math.atan(math.tan(math.radians(camera.fov_deg) / 2.0) / zoom))
    return camera.model_copy(update={"position": tuple(position), "fov_deg": fov})


def _rise(
    points: EdgePoints, target_gray: np.ndarray, truth: PinholeCamera, pixel: float = 1.0
) -> list[float]:
    """The valley's cost at each of :data:`ZOOMS` over its least (module docstring), on a film
    ``pixel`` times the target's pixels."""
    levels = [target_level(target_gray, *level) for level in dense.pyramid(pixel)]
    fine = levels[-1]
    k = Intrinsics(truth.fx, truth.fy, truth.cx, truth.cy)
    rotation = np.asarray(truth.rotation)
    rvec, _ = cv2.Rodrigues(rotation)
    x = np.concatenate([rvec.ravel(), np.asarray(truth.translation), [1.0]])
    depth = float(np.median(points.world @ rotation[2] + x[5]))
    costs = []
    for zoom in ZOOMS:
        start = dense._zoomed(x, zoom, depth)
        kz = Intrinsics(k.fx * zoom, k.fy * zoom, k.cx, k.cy)
        fitted = dense._align(points, levels, kz, None, start[:6])
        residuals = ChamferProblem(points, fine, kz, None, False).residuals(fitted)
        costs.append(level_fit.level_cost(residuals, fine.sigma))
    least = min(costs)
    return [c / least for c in costs]


def measure(
    n: int, seeds: list[int], random_scenes: int, scale: int = 1, enlarge: bool = False
) -> None:
    """Measure and print (module docstring)."""
    pixel = float(scale) if enlarge else 1.0
    rises: dict[Band, list[list[float]]] = defaultdict(list)
    errors: dict[Band, list[float]] = defaultdict(list)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        ids_per_seed = {}
        for seed in seeds:
            ids = ["demo"]
            for i in range(random_scenes):
                ids.append(f"rand{seed}-{i}")
                generate_scene(np.random.default_rng([seed, i]), folder, ids[-1])
            ids_per_seed[seed] = ids
        catalog = SceneCatalog([*RendererSettings().scene_directories(), folder])
        with LocalRenderer(catalog) as renderer:
            for seed in seeds:
                for target in _targets(renderer, catalog, ids_per_seed[seed], n, seed):
                    bgr = _decoded(_target_image(renderer, target, 1 if enlarge else scale))
                    gray = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
                    if enlarge:
                        gray = on_film(gray, (gray.shape[1] * scale, gray.shape[0] * scale))
                    rgb, depth, near, truth = _render(renderer, target, target.camera, scale)
                    points, _ = edge_points_by_outline(rgb, depth, truth, None, near)
                    if len(points.world) < level_fit.MIN_POINTS:
                        continue
                    rises[target.band].append(_rise(points, gray, truth, pixel))
                    assert target.camera.fov_deg is not None
                    for zoom in OFF:
                        view = _dolly(target, zoom)
                        rgb, depth, near, start = _render(renderer, target, view, scale)
                        fit = dense.refine_dense(
                            gray, rgb, depth, start, fit_focal=True, near=near, pixel=pixel
                        )
                        fov = fit.intrinsics.fov_deg(truth.width)
                        errors[target.band].append(abs(fov / target.camera.fov_deg - 1.0))
                    print(f"  {target.scene} #{target.index} {target.band}", flush=True)
    header = " ".join(f"rise@{z:<5}" for z in SHOWN)
    print(f"\n{'band':6s} {'n':>3s} {header}  free fit ≤1 % fov  ≤2 % fov")
    for band in BANDS:
        if not rises[band]:
            continue
        table = np.array(rises[band])
        shown = " ".join(f"{np.median(table[:, ZOOMS.index(z)]):<10.3f}" for z in SHOWN)
        fits = np.array(errors[band])
        print(
            f"{band:6s} {len(table):3d} {shown}  {np.mean(fits <= 0.01):16.0%}  "
            f"{np.mean(fits <= 0.02):8.0%}"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=8, help="targets per scene")
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--random-scenes", type=int, default=2)
    parser.add_argument(
        "--scale", type=int, default=1, help="the target and views on a film this many times over"
    )
    parser.add_argument(
        "--enlarge",
        action="store_true",
        help="with --scale: the target at its own film, its grey enlarged to the views'",
    )
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    measure(args.n, seeds, args.random_scenes, args.scale, args.enlarge)


if __name__ == "__main__":
    main()
