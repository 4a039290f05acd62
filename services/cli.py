"""The ``cosmos`` command: render views, list scenes, run the demo.

* ``cosmos scenes [--url URL]``: the scenes (local files, or a running renderer);
* ``cosmos render --scene demo --theta 40 --phi 120 -o target.png``: one view, rendered in this
  process or by a renderer at ``--url``; ``--annotations FILE`` also writes its ground truth;
* ``cosmos demo``: starts a real renderer process on loopback, renders the demo scene from a random
  grid pose over HTTP with its ground truth, prints what it found and stops the renderer.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from services.common.errors import ServiceError
from services.common.launch import running_service
from services.common.models import PoseQuery, RenderAnnotations, RenderRequest
from services.renderer.catalog import BUILTIN_SCENES_DIR, SceneCatalog, scene_grid
from services.renderer.client import RendererClient, RendererError
from services.renderer.settings import RendererSettings

__all__ = ["main"]


def _pose_query(args: argparse.Namespace) -> PoseQuery:
    if args.lat is not None or args.lon is not None:
        return PoseQuery(lat=args.lat, lon=args.lon)
    return PoseQuery(theta_deg=args.theta, phi_deg=args.phi)


def _cmd_scenes(args: argparse.Namespace) -> int:
    if args.url:
        with RendererClient(args.url) as client:
            for summary in client.scenes():
                print(
                    f"{summary.id:<16} {summary.objects:>3} objects  {summary.grid_size:>5} poses"
                )
        return 0
    catalog = SceneCatalog(RendererSettings().scene_directories())
    for scene_id in catalog.ids():
        scene = catalog.get(scene_id)
        print(
            f"{scene_id:<16} {len(scene.spec.objects):>3} objects  "
            f"{scene_grid(scene).size:>5} poses  {scene.path}"
        )
    for scene_id, error in catalog.invalid().items():
        print(f"{scene_id:<16} INVALID: {error}")
    return 0


def _render_local(request: RenderRequest) -> tuple[bytes, RenderAnnotations | None, str]:
    from services.renderer.engine import RenderEngine
    from services.renderer.imaging import encode_png
    from services.renderer.view import resolve_view

    settings = RendererSettings()
    view = resolve_view(SceneCatalog(settings.scene_directories()), settings, request)
    engine = RenderEngine(settings.mitsuba_variant)
    engine.start()
    try:
        image = engine.render(view.scene, view.pose, view.width, view.height, view.spp, view.seed)
        ann = engine.annotate(view.scene, view.pose, view.width, view.height, view.grid_index)
        return encode_png(image.rgb), ann, engine.variant
    finally:
        engine.close()


def _cmd_render(args: argparse.Namespace) -> int:
    request = RenderRequest(
        scene=args.scene,
        pose=_pose_query(args),
        width=args.width,
        height=args.height,
        spp=args.spp,
        seed=args.seed,
    )
    if args.url:
        with RendererClient(args.url) as client:
            png = client.render_png(request)
            ann = client.annotations(request) if args.annotations else None
        where = args.url
    else:
        png, ann, where = _render_local(request)
    Path(args.output).write_bytes(png)
    print(f"wrote {args.output} ({len(png)} bytes, {where})")
    if args.annotations and ann is not None:
        Path(args.annotations).write_text(ann.model_dump_json(indent=2))
        print(f"wrote {args.annotations}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get("demo")
    grid = scene_grid(scene)
    rng = random.Random(args.seed)
    index = grid.unflat(rng.randrange(grid.size))
    pose = grid.pose(index)
    print(f"demo scene: {len(scene.spec.objects)} objects, {grid.size} grid poses")
    print(
        f"target pose: lat {index.lat}, lon {index.lon} "
        f"(θ {pose.theta_deg:.1f}°, φ {pose.phi_deg:.1f}°)"
    )
    started = time.perf_counter()
    with (
        tempfile.TemporaryDirectory() as logs,
        running_service("services.renderer.app:app", Path(logs)) as renderer,
        RendererClient(renderer.url) as client,
    ):
        print(f"renderer up at {renderer.url} in {time.perf_counter() - started:.1f} s")
        request = RenderRequest(scene="demo", pose=PoseQuery(lat=index.lat, lon=index.lon))
        png = client.render_png(request)
        ann = client.annotations(request)
    (out / "demo-target.png").write_bytes(png)
    (out / "demo-target.json").write_text(ann.model_dump_json(indent=2))
    print(f"rendered {out / 'demo-target.png'} and its ground truth {out / 'demo-target.json'}")
    for obj in ann.objects:
        box = "not visible" if obj.box is None else "box " + ", ".join(f"{v:.0f}" for v in obj.box)
        print(f"  {obj.name:<8} {box:<24} {obj.visible_fraction:>5.0%} visible")
    print(f"total {time.perf_counter() - started:.1f} s")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cosmos", description="COSMOS 3D Search")
    commands = parser.add_subparsers(dest="command", required=True)

    scenes = commands.add_parser("scenes", help="list the scenes")
    scenes.add_argument("--url", help="ask a running renderer instead of reading the files")
    scenes.set_defaults(run=_cmd_scenes)

    render = commands.add_parser("render", help="render one view of a scene to a PNG")
    render.add_argument("--scene", default="demo")
    render.add_argument("--theta", type=float, default=45.0, help="polar angle θ in degrees")
    render.add_argument("--phi", type=float, default=0.0, help="azimuth φ in degrees")
    render.add_argument("--lat", type=int, help="grid ring index (with --lon, instead of angles)")
    render.add_argument("--lon", type=int, help="grid position on the ring")
    render.add_argument("--width", type=int)
    render.add_argument("--height", type=int)
    render.add_argument("--spp", type=int)
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("-o", "--output", default="view.png")
    render.add_argument("--annotations", help="also write the view's ground truth JSON here")
    render.add_argument("--url", help="use a running renderer instead of rendering in-process")
    render.set_defaults(run=_cmd_render)

    demo = commands.add_parser("demo", help="render the demo scene through a real renderer")
    demo.add_argument("--out", default="out")
    demo.add_argument("--seed", type=int, help="seed of the random target pose")
    demo.set_defaults(run=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cosmos``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        status: int = args.run(args)
    except ServiceError as exc:
        print(f"cosmos: {exc.detail}", file=sys.stderr)
        return 2
    except (RendererError, RuntimeError, ValueError) as exc:
        print(f"cosmos: {exc}", file=sys.stderr)
        return 1
    return status


if __name__ == "__main__":
    sys.exit(main())
