"""``python -m cosmos.bench.free_targets --scene demo --n 20 --seed 1``: draw free targets, run
the baseline and the box-only bound on them, print the table per elevation band and per count
of objects in view."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from cosmos.bench.free_targets.draw import DrawError, draw_targets
from cosmos.bench.free_targets.rendering import LocalRenderer, Renderer
from cosmos.bench.free_targets.report import evaluate, text_table
from cosmos.bench.free_targets.shapes import scene_shapes
from services.common.auth import token_from_environment
from services.common.catalog import SceneCatalog
from services.common.errors import ServiceError
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
    return parser


def _run(args: argparse.Namespace, renderer: Renderer, catalog: SceneCatalog) -> None:
    results = []
    for scene_id in args.scene or ["demo"]:
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
        results += evaluate(targets, shapes, scene.spec.camera.radius, args.seed)
        sys.stderr.write(
            f"{scene_id}: {len(targets)} targets drawn in {drawn_s:.1f} s, "
            f"{sum(not t.intrinsics_given for t in targets)} without intrinsics\n"
        )
    sys.stdout.write(text_table(results) + "\n\n" + text_table(results, by="objects") + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    settings = RendererSettings()
    catalog = SceneCatalog(settings.scene_directories())
    try:
        if args.url:
            with RendererClient(args.url, token=token_from_environment()) as client:
                _run(args, client, catalog)
        else:
            with LocalRenderer(catalog, settings) as local:
                _run(args, local, catalog)
    except ServiceError as exc:
        sys.stderr.write(f"free targets: {exc.detail}\n")
        return 2
    except (DrawError, RendererError) as exc:
        sys.stderr.write(f"free targets: {exc}\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
