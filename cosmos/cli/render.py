"""``cosmos render --scene demo --theta 40 --phi 120 -o target.png``: one view, rendered in this
process or by a renderer at ``--url``; ``--annotations FILE`` also writes its ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from cosmos.cli.common import Commands
from services.common.auth import token_from_environment
from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.geometry.pose import PoseQuery
from services.renderer.client import RendererClient
from services.renderer.settings import RendererSettings

__all__ = ["register", "run"]


def _pose_query(args: argparse.Namespace) -> PoseQuery:
    if args.lat is not None or args.lon is not None:
        return PoseQuery(lat=args.lat, lon=args.lon)
    return PoseQuery(theta_deg=args.theta, phi_deg=args.phi)


def _render_local(request: RenderRequest) -> tuple[bytes, RenderAnnotations | None, str]:
    from services.renderer.engine import RenderEngine
    from services.renderer.imaging import encode_png
    from services.renderer.view import resolve_view

    settings = RendererSettings()
    view = resolve_view(SceneCatalog(settings.scene_directories()), settings, request)
    engine = RenderEngine(settings.renderer_mitsuba_variant)
    engine.start()
    try:
        image = engine.render(view.scene, view.pose, view.width, view.height, view.spp, view.seed)
        ann = engine.annotate(view.scene, view.pose, view.width, view.height, view.grid_index)
        return encode_png(image.rgb), ann, engine.variant
    finally:
        engine.close()


def run(args: argparse.Namespace) -> int:
    request = RenderRequest(
        scene=args.scene,
        pose=_pose_query(args),
        width=args.width,
        height=args.height,
        spp=args.spp,
        seed=args.seed,
    )
    if args.url:
        with RendererClient(args.url, token=token_from_environment()) as client:
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


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
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
    render.set_defaults(run=run)
