"""``cosmos render --scene demo --theta 40 --phi 120 -o target.png``: one view, rendered in this
process or by a renderer at ``--url``; ``--annotations FILE`` also writes its ground truth.

A free camera instead of a hemisphere pose: ``--position X,Y,Z`` with one orientation,
``--ypr YAW,PITCH,ROLL``, ``--look-at X,Y,Z [--roll DEG]`` or ``--quaternion W,X,Y,Z``, and
optionally ``--fov DEG`` or ``--intrinsics FX,FY,CX,CY`` and ``--distortion K1,K2,P1,P2[,K3]``
(:class:`~services.common.geometry.free_camera.FreeCamera` states the conventions).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cosmos.cli.common import Commands, accept_negative_lists
from services.common.auth import token_from_environment
from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.common.geometry.pose import PoseQuery
from services.renderer.client import RendererClient
from services.renderer.settings import RendererSettings

__all__ = ["free_camera_of_args", "register", "run"]

_FREE_ONLY = ("ypr", "look_at", "quaternion", "roll", "fov", "intrinsics", "distortion")
"""Flags that only mean something for a free camera (``--position``)."""


def _numbers(flag: str, text: str, count: int, names: str, optional: int = 0) -> tuple[float, ...]:
    """``count`` (up to ``count + optional``) finite comma-separated numbers from ``text``, or a
    ValueError naming ``flag``."""
    parts = text.split(",")
    try:
        values = tuple(float(part) for part in parts)
    except ValueError:
        values = ()
    if not count <= len(values) == len(parts) <= count + optional:
        counts = f"{count} or {count + optional}" if optional == 1 else str(count)
        raise ValueError(f"{flag} takes {counts} comma-separated numbers {names}, not {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag} takes finite numbers, not {text!r}")
    return values


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _one_line(exc: ValidationError) -> str:
    """A pydantic error as one line: each problem's field and message."""
    problems = []
    for error in exc.errors():
        where = ".".join(str(part) for part in error["loc"])
        problems.append(f"{where}: {error['msg']}" if where else str(error["msg"]))
    return "invalid camera: " + "; ".join(problems)


def free_camera_of_args(args: argparse.Namespace) -> FreeCamera:
    """The free camera the flags give (``--position`` and one orientation, optional lens).

    Raises
    ------
    ValueError
        A flag is not a list of finite numbers of the right length, the orientation is not given
        exactly once, or the camera does not validate (one line, naming the field).
    """
    fields: dict[str, Any] = {"position": _numbers("--position", args.position, 3, "X,Y,Z")}
    forms = [name for name in ("ypr", "look_at", "quaternion") if getattr(args, name) is not None]
    if len(forms) != 1:
        raise ValueError("--position needs exactly one of --ypr, --look-at and --quaternion")
    if args.ypr is not None:
        yaw, pitch, roll = _numbers("--ypr", args.ypr, 3, "YAW,PITCH,ROLL")
        fields.update(yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll)
    elif args.look_at is not None:
        fields["look_at"] = _numbers("--look-at", args.look_at, 3, "X,Y,Z")
    else:
        fields["quaternion_wxyz"] = _numbers("--quaternion", args.quaternion, 4, "W,X,Y,Z")
    if args.roll is not None:
        if args.look_at is None:
            raise ValueError("--roll goes with --look-at (--ypr carries its own roll)")
        fields["roll_deg"] = args.roll
    if args.fov is not None and args.intrinsics is not None:
        raise ValueError("give --fov or --intrinsics, not both")
    if args.fov is not None:
        fields["fov_deg"] = args.fov
    if args.intrinsics is not None:
        fx, fy, cx, cy = _numbers("--intrinsics", args.intrinsics, 4, "FX,FY,CX,CY")
        fields.update(fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy)
    if args.distortion is not None:
        lens = _numbers("--distortion", args.distortion, 4, "K1,K2,P1,P2[,K3]", optional=1)
        fields["distortion"] = LensDistortion.of_coefficients(lens)
    try:
        return FreeCamera(**fields)
    except ValidationError as exc:
        raise ValueError(_one_line(exc)) from None


def _request(args: argparse.Namespace) -> RenderRequest:
    """The render request of the flags: a free camera with ``--position``, else a hemisphere
    pose (angles, θ 45° and φ 0° by default, or grid indices)."""
    camera = pose = None
    if args.position is not None:
        pose_flags = [f for f in ("theta", "phi", "lat", "lon") if getattr(args, f) is not None]
        if pose_flags:
            raise ValueError(f"--position is a free camera: drop {_flag(pose_flags[0])}")
        camera = free_camera_of_args(args)
    else:
        free_flags = [f for f in _FREE_ONLY if getattr(args, f) is not None]
        if free_flags:
            raise ValueError(f"{_flag(free_flags[0])} needs a free camera: give --position too")
        if args.lat is not None or args.lon is not None:
            pose = PoseQuery(lat=args.lat, lon=args.lon)
        else:
            theta = 45.0 if args.theta is None else args.theta
            pose = PoseQuery(theta_deg=theta, phi_deg=0.0 if args.phi is None else args.phi)
    try:
        return RenderRequest(
            scene=args.scene,
            pose=pose,
            camera=camera,
            width=args.width,
            height=args.height,
            spp=args.spp,
            seed=args.seed,
        )
    except ValidationError as exc:
        raise ValueError(_one_line(exc).replace("invalid camera", "invalid request")) from None


def _render_local(
    request: RenderRequest, annotate: bool
) -> tuple[bytes, RenderAnnotations | None, str]:
    from services.renderer.engine import RenderEngine
    from services.renderer.imaging import encode_png
    from services.renderer.view import resolve_view

    settings = RendererSettings()
    view = resolve_view(SceneCatalog(settings.scene_directories()), settings, request)
    engine = RenderEngine(settings.renderer_mitsuba_variant)
    engine.start()
    try:
        image = engine.render(view.scene, view.pose, view.width, view.height, view.spp, view.seed)
        ann = None
        if annotate:  # N + 1 mask renders: only when asked
            ann = engine.annotate(view.scene, view.pose, view.width, view.height, view.grid_index)
        return encode_png(image.rgb), ann, engine.variant
    finally:
        engine.close()


def run(args: argparse.Namespace) -> int:
    request = _request(args)
    if args.url:
        with RendererClient(args.url, token=token_from_environment()) as client:
            png = client.render_png(request)
            ann = client.annotations(request) if args.annotations else None
        where = args.url
    else:
        png, ann, where = _render_local(request, annotate=bool(args.annotations))
    Path(args.output).write_bytes(png)
    print(f"wrote {args.output} ({len(png)} bytes, {where})")
    if args.annotations and ann is not None:
        Path(args.annotations).write_text(ann.model_dump_json(indent=2))
        print(f"wrote {args.annotations}")
    return 0


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    render = commands.add_parser(
        "render",
        help="render one view of a scene to a PNG",
        description="Render one view: a hemisphere pose (--theta/--phi or --lat/--lon) or a free "
        "camera (--position with --ypr, --look-at or --quaternion). World frame: z up, the "
        "ground at z = 0; camera axes x right, y down, z forward.",
    )
    accept_negative_lists(render)
    hemisphere = render.add_argument_group("hemisphere pose (the default: θ 45°, φ 0°)")
    hemisphere.add_argument("--theta", type=float, help="polar angle θ in degrees (default 45)")
    hemisphere.add_argument("--phi", type=float, help="azimuth φ in degrees (default 0)")
    hemisphere.add_argument("--lat", type=int, help="grid ring index (with --lon, not angles)")
    hemisphere.add_argument("--lon", type=int, help="grid position on the ring")
    free = render.add_argument_group("free camera")
    free.add_argument("--position", metavar="X,Y,Z", help="camera centre in scene units")
    free.add_argument(
        "--ypr",
        metavar="YAW,PITCH,ROLL",
        help="degrees: yaw counter-clockwise from +x, pitch below the horizontal (90 = nadir), "
        "roll about the optical axis",
    )
    free.add_argument(
        "--look-at", metavar="X,Y,Z", help="world point the optical axis goes through"
    )
    free.add_argument("--roll", type=float, metavar="DEG", help="roll with --look-at, degrees")
    free.add_argument(
        "--quaternion", metavar="W,X,Y,Z", help="camera-to-world rotation (normalised)"
    )
    free.add_argument(
        "--fov", type=float, metavar="DEG", help="horizontal field of view (the scene's default)"
    )
    free.add_argument(
        "--intrinsics", metavar="FX,FY,CX,CY", help="OpenCV intrinsics in pixels of the film"
    )
    free.add_argument("--distortion", metavar="K1,K2,P1,P2[,K3]", help="OpenCV lens distortion")
    render.add_argument("--scene", default="demo")
    render.add_argument("--width", type=int, help="film width in pixels (the scene's default)")
    render.add_argument("--height", type=int, help="film height in pixels")
    render.add_argument("--spp", type=int)
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("-o", "--output", default="view.png")
    render.add_argument("--annotations", help="also write the view's ground truth JSON here")
    render.add_argument("--url", help="use a running renderer instead of rendering in-process")
    render.set_defaults(run=run)
