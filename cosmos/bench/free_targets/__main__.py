"""``python -m cosmos.bench.free_targets --scene demo --random-scenes 4 --n 20 --seed 1``: draw
free targets, run the baseline, the box-only bound, the box solver and the dense stage after it
(one render per target, on each image variant) on them, print the table per elevation band, per
given or estimated intrinsics and per count of objects in view, the solver's statuses and the
dense stage's renders and time.

``--random-scenes N`` adds N scenes of :func:`cosmos.bench.scenes.generate_scene` (scene ``i``
from the seed ``[seed, i]``, written to a temporary folder): their targets are tabled together
as scene "random", then each scene's totals. A scene where targets cannot be drawn
(:class:`DrawError`) is reported and skipped."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from cosmos.bench.free_targets.draw import DrawError, draw_targets
from cosmos.bench.free_targets.rendering import LocalRenderer, Renderer
from cosmos.bench.free_targets.report import (
    TargetResult,
    dense_line,
    evaluate,
    solver_table,
    text_table,
)
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.scenes import generate_scenes
from services.common.auth import token_from_environment
from services.common.catalog import SceneCatalog
from services.common.errors import ServiceError
from services.optimizer.free import scene_objects
from services.renderer.client import RendererClient, RendererError
from services.renderer.settings import RendererSettings


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m cosmos.bench.free_targets",
        description="Free targets (issue 23, item 5): the plain solvePnPRansac baseline and the "
        "ideal box-only fit per elevation band.",
    )
    parser.add_argument("--scene", action="append", help="a scene id (repeatable; demo)")
    parser.add_argument("--n", type=int, default=20, help="targets per scene")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--width", type=int, help="film width (the scene camera's by default)")
    parser.add_argument("--height", type=int)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--url", help="a running renderer instead of rendering in-process")
    parser.add_argument(
        "--dense-renders",
        type=int,
        default=1,
        metavar="N",
        help="renders the dense stage spends per target (0: no dense stage)",
    )
    parser.add_argument(
        "--random-scenes",
        type=int,
        default=0,
        metavar="N",
        help="also N generated scenes (local renderer only), tabled together as 'random'",
    )
    return parser


def _scene_results(
    args: argparse.Namespace, renderer: Renderer, catalog: SceneCatalog, scene_id: str
) -> list[TargetResult]:
    scene = catalog.get(scene_id)
    shapes = scene_shapes(scene)
    started = time.perf_counter()
    targets = draw_targets(
        renderer,
        scene,
        shapes,
        args.n,
        args.seed,
        width=args.width,
        height=args.height,
        spp=args.spp,
    )
    drawn_s = time.perf_counter() - started
    objects = scene_objects(scene.spec, scene.assets)
    results = evaluate(
        targets,
        shapes,
        scene.spec.camera.radius,
        args.seed,
        objects,
        renderer if args.dense_renders > 0 else None,
        spp=args.spp,
        renders=max(args.dense_renders, 1),
    )
    sys.stderr.write(
        f"{scene_id}: {len(targets)} targets drawn in {drawn_s:.1f} s, solved in "
        f"{time.perf_counter() - started - drawn_s:.1f} s, "
        f"{sum(not t.intrinsics_given for t in targets)} without intrinsics\n"
    )
    return results


def _run(
    args: argparse.Namespace,
    renderer: Renderer,
    catalog: SceneCatalog,
    random_ids: Sequence[str] = (),
) -> None:
    results: list[TargetResult] = []
    for scene_id in args.scene or ([] if random_ids else ["demo"]):
        results += _scene_results(args, renderer, catalog, scene_id)
    randoms: list[TargetResult] = []
    skipped = []
    for scene_id in random_ids:
        try:
            randoms += _scene_results(args, renderer, catalog, scene_id)
        except DrawError as exc:
            skipped.append(scene_id)
            sys.stderr.write(f"free targets: skipped: {exc}\n")
    results += [replace(r, scene="random") for r in randoms]
    out = [
        text_table(results),
        text_table(results, by="given"),
        text_table(results, by="objects"),
        solver_table(results),
    ]
    if args.dense_renders > 0:
        out.append(dense_line(results))
    if randoms:
        out += [text_table(randoms, totals_only=True), solver_table(randoms)]
    if skipped:
        out.append(f"skipped (no targets drawn): {', '.join(skipped)}")
    sys.stdout.write("\n\n".join(out) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.random_scenes and args.url:
        sys.stderr.write("free targets: --random-scenes renders in-process: leave out --url\n")
        return 2
    settings = RendererSettings()
    try:
        with tempfile.TemporaryDirectory(prefix="cosmos-free-scenes-") as tmp:
            random_ids = generate_scenes(args.random_scenes, args.seed, Path(tmp))
            directories = settings.scene_directories() + ([Path(tmp)] if random_ids else [])
            catalog = SceneCatalog(directories)
            if args.url:
                with RendererClient(args.url, token=token_from_environment()) as client:
                    _run(args, client, catalog)
            else:
                with LocalRenderer(catalog, settings) as local:
                    _run(args, local, catalog, random_ids)
    except ServiceError as exc:
        sys.stderr.write(f"free targets: {exc.detail}\n")
        return 2
    except (DrawError, RendererError) as exc:
        sys.stderr.write(f"free targets: {exc}\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
