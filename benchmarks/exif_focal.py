"""A camera's JPEG through the real stack: its fov given, its EXIF focal length read, or neither.

Run: ``.venv/bin/python -m benchmarks.exif_focal [--scenes demo,garden] [--n 8] [--seed 3]``

A local stack (:func:`cosmos.stack.local_stack`) serves the searches. Per scene, ``--n`` drone
views are drawn at random (distance 0.5-1.2 of the scene radius, elevation 35-88°, looking near
the centre, roll within ±20°, fov 45-75°), rendered at 640 × 480 and stored as JPEGs whose EXIF
states ``FocalLengthIn35mmFilm`` rounded to the millimetre, as cameras write it. Each is
searched four ways (``mode=free``): with ``fov_deg`` exact; with nothing (the EXIF read); with
nothing, its EXIF stating a focal length 15 % too long; and with ``exif=false`` (the focal
length estimated from the boxes). It prints per way the shares
within 5 % of the radius and 2°, and within 2 % and 1°, the median position error and how
many answers were confirmed.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from pathlib import Path

import numpy as np

from cosmos.bench.variants import exif_jpeg
from cosmos.stack import local_stack
from services.common.contracts.render import RenderAnnotations
from services.common.contracts.search import Search
from services.common.geometry.free_camera import FreeCamera, orbit_position
from services.controller.client import ControllerClient
from services.renderer.client import RendererClient

WAYS = ("fov given", "EXIF read", "EXIF 15 % long", "EXIF not read")
WRONG_EXIF = 1.15
"""The wrong EXIF's focal length, as a share of the true one (a crop whose EXIF says nothing of
it, a digital zoom left out)."""


def drone(rng: np.random.Generator, radius: float) -> FreeCamera:
    distance = rng.uniform(0.5, 1.2) * radius
    elevation = float(rng.uniform(35.0, 88.0))
    azimuth = math.degrees(rng.uniform(0.0, 2.0 * math.pi))
    position = orbit_position((0.0, 0.0, 0.0), distance, elevation, azimuth)
    return FreeCamera(
        position=position,
        look_at=(rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), 0.0),
        roll_deg=rng.uniform(-20.0, 20.0),
        fov_deg=rng.uniform(45.0, 75.0),
    )


def errors(search: Search, truth: RenderAnnotations, radius: float) -> tuple[float, float]:
    """Position error (share of the radius) and rotation error (degrees) of the answer."""
    if search.result is None or search.result.free is None:
        return math.inf, math.inf
    pose = search.result.free.pose
    found = FreeCamera(position=(0.0, 0.0, 1.0), quaternion_wxyz=pose.quaternion_wxyz).rotation()
    relative = found.T @ np.asarray(truth.camera.rotation).T
    turned = math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
    return math.dist(pose.position, truth.camera.position) / radius, turned


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="demo,garden")
    parser.add_argument("--n", type=int, default=8)
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args(argv)
    rows: dict[str, list[tuple[float, float, bool]]] = {way: [] for way in WAYS}
    with tempfile.TemporaryDirectory() as work, local_stack(Path(work)) as stack:
        renderer = RendererClient(stack.renderers[0], token=stack.service_token)
        client = ControllerClient(stack.controller, api_key=stack.api_key)
        with renderer, client:
            for scene in args.scenes.split(","):
                radius = renderer.scene(scene).spec.camera.radius
                rng = np.random.default_rng([args.seed, len(scene)])
                for _ in range(args.n):
                    camera = drone(rng, radius)
                    png, truth = renderer.render_camera(scene, camera, width=640, height=480)
                    k = truth.camera
                    f35 = round(k.fx * math.hypot(36.0, 24.0) / math.hypot(k.width, k.height))
                    for way in WAYS:
                        stated = round(f35 * WRONG_EXIF) if way == "EXIF 15 % long" else f35
                        search = client.submit(
                            exif_jpeg(png, stated),
                            scene,
                            mode="free",
                            fov_deg=k.fov_deg if way == "fov given" else None,
                            exif="false" if way == "EXIF not read" else None,
                        )
                        for _ in client.follow(search.id, timeout_s=120):
                            pass
                        final = client.get(search.id)
                        moved, turned = errors(final, truth, radius)
                        found = final.result is not None and final.result.confirmed
                        rows[way].append((moved, turned, found))
    for way, done in rows.items():
        within5 = sum(m <= 0.05 and t <= 2.0 for m, t, _ in done) / len(done)
        within2 = sum(m <= 0.02 and t <= 1.0 for m, t, _ in done) / len(done)
        median = statistics.median(m for m, _, _ in done)
        confirmed = sum(f for _, _, f in done)
        print(
            f"{way:14s} {len(done)} views: {within5:.0%} within 5 %/2°, {within2:.0%} within "
            f"2 %/1°, median position error {100 * median:.2f} % of the radius, "
            f"{confirmed} confirmed"
        )


if __name__ == "__main__":
    main()
