"""Does one render's dense fit settle a hemisphere answer between grid poses?

Run: ``.venv/bin/python -m benchmarks.grid_edges [--n 8] [--seeds 41,42] [--random-scenes 2]``

A hemisphere search whose answer is not confirmed renders that answer's pose once more, with
its depth, and lets the optimizer's dense fit move the render's edges onto the target's; the
answer becomes the grid pose nearest the camera it ends at when the fit settles it
(:mod:`services.controller.grid_edges`). This measures that rule as shipped: the optimizer's
``refine_pose`` and the controller's ``settled_result``, in one process.

Targets: off-grid poses (``cosmos.bench.variants``' ``offgrid`` draw: up to a third of a step
from a grid pose) of the demo and of ``--random-scenes`` generated scenes per seed, clean and
with pixel noise. Each is fitted from a render at its true grid pose (an answer a search got
right, unconfirmed) and at each of that pose's neighbours (one it got wrong). Per θ band and
start it prints how many fits settled the answer, and of those how many at the true grid pose;
the answers right before and after; the settled direction's median angle to the target's; and
the median milliseconds per fit.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np

from benchmarks.seeded import seeded_scenes
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.variants import Variant, degrade, draw_pose
from services.common.catalog import SceneCatalog
from services.common.contracts.optimize import GridPose, searchable_grid
from services.common.contracts.refine import RefinePoseRequest
from services.common.contracts.render import RenderRequest
from services.common.contracts.search import SearchResult
from services.common.depth_archive import DepthImage
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.pose import GridIndex, PoseQuery
from services.common.geometry.sphere import angular_distance_deg
from services.controller.free_refine import MIN_PIN_POINTS
from services.controller.grid_edges import ON_SPHERE, SETTLE_SHARE, grid_free_pose, settled_result
from services.optimizer.free_pose import SceneObjectCache
from services.optimizer.refine_pose import ImageLimits, refine_pose

VARIANTS: tuple[Variant, ...] = ("clean", "noise")
BANDS = ((0.0, 30.0, "θ < 30°"), (30.0, 60.0, "30-60°"), (60.0, 90.1, "θ > 60°"))
RULES: tuple[tuple[float, float, int], ...] = (
    (SETTLE_SHARE, ON_SPHERE, MIN_PIN_POINTS),
    *(
        (share, on, MIN_PIN_POINTS)
        for share in (0.5, 0.7, 0.9)
        for on in (0.005, 0.01, 0.02, 0.05)
        if (share, on) != (SETTLE_SHARE, ON_SPHERE)
    ),
    *((SETTLE_SHARE, ON_SPHERE, points) for points in (50, 100)),
)
"""The (share, on-sphere, least edge points) bounds tried: the shipped ones first."""
VIEW_SPP = 8
"""The searches' views' samples per pixel (the controller's default)."""


@dataclass(frozen=True)
class Fit:
    """One fit from a render at ``start``: whether it settled the answer, where, how far off."""

    rule: tuple[float, float, int]
    band: str
    from_truth: bool
    settled: bool
    right_after: bool
    angle_deg: float
    ms: float


def _band(theta: float) -> str:
    return next(name for low, high, name in BANDS if low <= theta < high)


def _archive(renderer: LocalRenderer, scene: str, index: GridIndex, seed: int) -> bytes:
    """The render at grid pose ``index`` with its depth, as the renderer's archive."""
    request = RenderRequest(
        scene=scene, pose=PoseQuery(lat=index.lat, lon=index.lon), spp=VIEW_SPP, seed=seed
    )
    geometry = renderer.depth(request)
    bgr = cv2.imdecode(np.frombuffer(renderer.render_png(request), np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the renderer's PNG does not decode")
    rgb = np.ascontiguousarray(bgr[..., ::-1], dtype=np.uint8)
    return DepthImage(geometry.depth, geometry.objects, rgb, geometry.shading).npz()


def _fits(
    renderer: LocalRenderer, catalog: SceneCatalog, scene_id: str, n: int, seed: int
) -> list[Fit]:
    scene = catalog.get(scene_id)
    camera = scene.spec.camera
    grid = searchable_grid(scene.spec.search)
    hemisphere: HemisphereGrid = grid.grid()
    rng = np.random.default_rng([seed, n])
    cache, limits = SceneObjectCache(), ImageLimits(max_pixels=4096 * 4096, max_side=4096)
    fits: list[Fit] = []
    for k in range(n):
        drawn = draw_pose(hemisphere, "offgrid", rng)
        query = PoseQuery(theta_deg=drawn.pose.theta_deg, phi_deg=drawn.pose.phi_deg)
        png = renderer.render_png(RenderRequest(scene=scene_id, pose=query, seed=k))
        starts = [drawn.truth, *hemisphere.neighbours(drawn.truth).values()]
        archives = {s: _archive(renderer, scene_id, s, k) for s in starts}
        for variant in VARIANTS:
            image = degrade(png, variant, rng)
            for start in starts:
                at = hemisphere.pose(start)
                pose = grid_free_pose(
                    at, camera.radius, camera.fov_deg, (camera.width, camera.height)
                )
                request = RefinePoseRequest(scene=scene_id, pose=pose)
                began = time.perf_counter()
                outcome = refine_pose(request, image, archives[start], catalog, cache, limits)
                ms = (time.perf_counter() - began) * 1000.0
                answer = SearchResult(
                    pose=GridPose(index=start, theta_deg=at.theta_deg, phi_deg=at.phi_deg),
                    refined_pose=at,
                    confidence=0.0,
                    renders=1,
                    confirmed=False,
                )
                for bounds in RULES:
                    share, on_sphere, points = bounds
                    settled = settled_result(
                        answer,
                        outcome,
                        grid,
                        camera.radius,
                        share=share,
                        on_sphere=on_sphere,
                        min_points=points,
                    )
                    fits.append(
                        Fit(
                            rule=bounds,
                            band=_band(drawn.pose.theta_deg),
                            from_truth=start == drawn.truth,
                            settled=settled.refined_pose != at,
                            right_after=settled.pose.index == drawn.truth,
                            angle_deg=float(angular_distance_deg(settled.refined_pose, drawn.pose)),
                            ms=ms,
                        )
                    )
    return fits


def _print(fits: list[Fit]) -> None:
    shipped = [f for f in fits if f.rule == RULES[0]]
    print(
        f"share {SETTLE_SHARE:g}, camera within {ON_SPHERE:.1%} of the radius, at least "
        f"{MIN_PIN_POINTS} edge points (as shipped):\n"
    )
    _print_rule(shipped)
    print(
        f"\nmedian ms per fit: {statistics.median(f.ms for f in shipped):.0f} ({len(shipped)} fits)"
    )
    print(
        "\nother bounds: settled answers, at the truth, from the true grid pose and a neighbour:\n"
    )
    print(
        "| share | within % of the radius | least edge points | from the truth: settled (right) "
        "| from a neighbour: settled (right) |"
    )
    print("|---|---|---|---|---|")
    for rule in RULES[1:]:
        mine = [f for f in fits if f.rule == rule]
        cells = []
        for from_truth in (True, False):
            settled = [f for f in mine if f.from_truth == from_truth and f.settled]
            total = sum(f.from_truth == from_truth for f in mine)
            cells.append(f"{len(settled)} of {total} ({sum(f.right_after for f in settled)})")
        print(f"| {rule[0]:g} | {rule[1]:.1%} | {rule[2]} | {cells[0]} | {cells[1]} |")


def _print_rule(fits: list[Fit]) -> None:
    groups: dict[tuple[str, str], list[Fit]] = defaultdict(list)
    for fit in fits:
        start = "true grid pose" if fit.from_truth else "a neighbour"
        for band in (fit.band, "all"):
            groups[(start, band)].append(fit)
    print(
        "| start | θ band | fits | settled | settled at the truth | right before → after "
        "| settled angle p50 ° |"
    )
    print("|---|---|---|---|---|---|---|")
    for start in ("true grid pose", "a neighbour"):
        for _, _, band in (*BANDS, (0, 0, "all")):
            group = groups.get((start, band), [])
            if not group:
                continue
            settled = [f for f in group if f.settled]
            right = sum(f.right_after for f in settled)
            before = len(group) if start == "true grid pose" else 0
            after = sum(f.right_after for f in group)
            angle = statistics.median(f.angle_deg for f in settled) if settled else math.nan
            print(
                f"| {start} | {band} | {len(group)} | {len(settled)} | {right} of {len(settled)} "
                f"| {before} → {after} | {angle:.2f} |"
            )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=8, help="targets per scene")
    parser.add_argument("--seeds", default="41,42")
    parser.add_argument("--random-scenes", type=int, default=2)
    args = parser.parse_args(argv)
    seeds = (int(s) for s in args.seeds.split(","))
    fits = [
        fit
        for renderer, catalog, scene_id, seed in seeded_scenes(seeds, args.random_scenes)
        for fit in _fits(renderer, catalog, scene_id, args.n, seed)
    ]
    _print(fits)


if __name__ == "__main__":
    main()
