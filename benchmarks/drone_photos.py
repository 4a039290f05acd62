"""Drone-sized photos through the real stack: free searches of 4000 x 3000 JPEGs, with and
without their intrinsics, at two view widths.

Run: ``.venv/bin/python -m benchmarks.drone_photos [--seeds 11,12,13] [--n 8]
[--view-widths 160,320]``

The free bench's targets are the scene camera's film (320 x 240 for the demo), so a search
renders its views as wide as the target. A drone's photo is far larger: the search renders at
its view width and brings the photo down to it. This measures what that width costs and buys.

Targets: the free bench's draw (``cosmos.bench.free_targets``: distance 0.4–1.6 radii,
elevation 10–90° with nadir views, roll ±25°, fov ±30 %) of the demo scene for each seed, each
rendered at ``--render-width`` (16 samples a pixel) and brought to ``--photo-width`` with cubic
interpolation, a JPEG of quality 92, no EXIF.

Arms: one local stack (``cosmos.stack.local_stack``: real renderer, detector, optimizer and
controller processes) per view width (``COSMOS_CONTROLLER_VIEW_WIDTH``); every photo searched
once with its fov given and once without. A search without intrinsics renders at twice its
view width (``services.controller.free_loop.FOCAL_VIEW_SCALE``), so the arm of width 160 shows
those searches as they were at 320, and the arm of 320 as they are now.

It prints per arm, intrinsics and elevation band: the answers within 5 %/2° and 2 %/1°, the
median fov error and the share within 2 %, the median wall time and renders, and how many were
confirmed (and confirmed while outside 5 %/2°).
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import aiohttp
import cv2
import numpy as np

from cosmos.bench.free_targets.draw import BANDS, draw_targets
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import PoseError, pose_error
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.runner import post_and_follow
from cosmos.stack import local_stack
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.geometry.free_camera import FreeCamera, rotation_of_quaternion

SCENE: Final = "demo"
TARGET_SPP: Final = 16


@dataclass(frozen=True)
class Photo:
    """One drone-sized target: its JPEG, the true camera and its elevation band."""

    jpeg: bytes
    camera: FreeCamera
    fov_deg: float
    band: str


@dataclass(frozen=True)
class Outcome:
    """One search: its error, wall time, renders and whether it was confirmed."""

    band: str
    given: bool
    error: PoseError
    wall_ms: float
    renders: int
    confirmed: bool

    @property
    def within(self) -> bool:
        return self.error.position <= 0.05 and self.error.rotation_deg <= 2.0


def photos(seeds: Sequence[int], n: int, render_width: int, photo_width: int) -> list[Photo]:
    """The targets of the module docstring."""
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    scene = catalog.get(SCENE)
    made = []
    with LocalRenderer(catalog) as renderer:
        for seed in seeds:
            for target in draw_targets(renderer, scene, scene_shapes(scene), n, seed):
                film = target.annotations.camera
                height = round(render_width * film.height / film.width)
                request = RenderRequest(
                    scene=SCENE,
                    camera=target.camera,
                    width=render_width,
                    height=height,
                    spp=TARGET_SPP,
                    seed=target.index,
                )
                png = renderer.render_png(request)
                bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise ValueError("the renderer's PNG does not decode")
                size = (photo_width, round(photo_width * film.height / film.width))
                big = cv2.resize(bgr, size, interpolation=cv2.INTER_CUBIC)
                ok, jpeg = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 92])
                assert ok
                made.append(Photo(jpeg.tobytes(), target.camera, film.fov_deg, target.band))
    return made


def answer_estimate(raw: dict[str, Any]) -> Estimate | None:
    """The free answer of a search's JSON ``raw`` as an estimate (None without one)."""
    result = raw.get("result") or {}
    pose = (result.get("free") or {}).get("pose")
    if not pose:
        return None
    return Estimate(
        rotation_of_quaternion(tuple(pose["quaternion_wxyz"])),
        np.asarray(pose["position"], dtype=np.float64),
        float(pose["intrinsics"]["fov_deg"]),
    )


async def _search(url: str, key: str, shots: Sequence[Photo], radius: float) -> list[Outcome]:
    outcomes = []
    headers = {"Authorization": f"Bearer {key}"}
    async with aiohttp.ClientSession(headers=headers) as http:
        for photo in shots:
            for given in (True, False):
                query = {"scene": SCENE, "mode": "free", "max_iterations": "5"}
                if given:
                    query["fov_deg"] = repr(photo.fov_deg)
                raw, wall_ms = await post_and_follow(http, url, photo.jpeg, query)
                truth = Estimate(
                    photo.camera.rotation(),
                    np.asarray(photo.camera.position, dtype=np.float64),
                    photo.fov_deg,
                )
                result = raw.get("result") or {}
                outcomes.append(
                    Outcome(
                        photo.band,
                        given,
                        pose_error(answer_estimate(raw), truth, radius),
                        wall_ms,
                        int(result.get("renders") or 0),
                        bool(result.get("confirmed")),
                    )
                )
    return outcomes


def header(first: str) -> str:
    """The table's header, ``first`` naming its first column."""
    return (
        f"{first:30s} {'n':>3s} {'≤5%/2°':>8s} {'≤2%/1°':>8s} {'fov med%':>7s} {'fov≤2%':>8s} "
        f"{'wall ms':>8s} {'renders':>7s} {'conf':>5s} {'wrong':>5s}"
    )


def print_bands(label: str, outcomes: Sequence[Outcome]) -> None:
    """A row of ``outcomes`` per elevation band that has any, then one of them all."""
    for band in BANDS:
        rows = [o for o in outcomes if o.band == band]
        if rows:
            print(row(f"{label} {band}", rows))
    print(row(f"{label} all", outcomes))


def row(label: str, rows: Sequence[Outcome]) -> str:
    """One table row of ``rows`` (under :func:`header`)."""
    n = len(rows)
    within = sum(r.within for r in rows)
    tight = sum(r.error.position <= 0.02 and r.error.rotation_deg <= 1.0 for r in rows)
    fov = [r.error.fov_pct for r in rows]
    near = sum(f <= 2.0 for f in fov)
    wall = statistics.median(r.wall_ms for r in rows)
    renders = statistics.median(r.renders for r in rows)
    confirmed = sum(r.confirmed for r in rows)
    wrong = sum(r.confirmed and not r.within for r in rows)
    return (
        f"{label:30s} {n:3d} {within:4d}/{n:<3d} {tight:4d}/{n:<3d} {statistics.median(fov):7.2f} "
        f"{near:4d}/{n:<3d} {wall:8.0f} {renders:7.1f} {confirmed:5d} {wrong:5d}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="11,12,13")
    parser.add_argument("--n", type=int, default=8, help="targets per seed")
    parser.add_argument("--view-widths", default="160,320")
    parser.add_argument("--render-width", type=int, default=1280)
    parser.add_argument("--photo-width", type=int, default=4000)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    shots = photos(seeds, args.n, args.render_width, args.photo_width)
    radius = SceneCatalog([BUILTIN_SCENES_DIR]).get(SCENE).spec.camera.radius
    print(f"{len(shots)} photos {args.photo_width} px wide of {SCENE}, seeds {args.seeds}")
    for width in (int(w) for w in args.view_widths.split(",")):
        env = {"COSMOS_CONTROLLER_VIEW_WIDTH": str(width)}
        with tempfile.TemporaryDirectory(prefix="cosmos-drone-") as tmp:
            with local_stack(Path(tmp), env=env) as stack:
                assert stack.api_key is not None
                outcomes = asyncio.run(_search(stack.controller, stack.api_key, shots, radius))
        print(f"\nview width {width} (searches without intrinsics render at {2 * width})")
        print(header("arm / intrinsics / band"))
        for given in (True, False):
            kind = "fov given" if given else "fov not given"
            print_bands(kind, [o for o in outcomes if o.given is given])


if __name__ == "__main__":
    main()
