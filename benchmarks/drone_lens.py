"""A drone's wide, distorted lens through the real stack: its calibration read from the photo's
XMP, its EXIF focal length alone, nothing read, or everything given.

Run: ``.venv/bin/python -m benchmarks.drone_lens [--scenes demo,garden] [--seeds 11] [--n 8]
[--render-width 1280] [--photo-width 4000] [--arms "EXIF only,no lens"] [--max-iterations 5]``

Survey drones shoot through wide lenses with barrel distortion and write the lens's calibration
into each photo's XMP (DJI's ``DewarpData``: :mod:`services.controller.photo_xmp`); the EXIF
only states a nominal focal length in whole millimetres.

Targets: the free bench's draw (``cosmos.bench.free_targets``: distance 0.4–1.6 radii, elevation
10–90° with nadir views, roll ±25°) of each scene and seed, with fields of view 1.3–1.8 times the
scene camera's (58–81° on the built-in scenes' 45°: a drone's wide camera). Each is rendered at
``--render-width`` (16 samples a pixel) through a drawn lens (:func:`drone_lens`: ``k1``
−0.25…−0.05, ``k2`` 0…0.1, ``k3`` −0.04…0, ``p1, p2`` within ±5·10⁻⁴, the principal point
within 1 % of the film's centre), brought to ``--photo-width`` (cubic) and written as a JPEG of
quality 92 whose EXIF states ``FocalLengthIn35mmFilm`` (rounded) and the original size, and
whose XMP states the calibration at that size and the gimbal's pitch and roll (the true ones,
each off by a seeded normal draw of :data:`GIMBAL_SIGMA_DEG`).

Arms, all through one local stack (``cosmos.stack.local_stack``), each photo searched once in
each with ``mode=free``:

- ``calibration``: the JPEG as the drone wrote it (the search reads the XMP: the lens, and the
  gimbal's attitude, which rules out poses of another tilt);
- ``EXIF only``: the same without its XMP packet (a nominal focal length, no lens);
- ``nothing read``: ``exif=false`` (the focal length estimated from the boxes, no lens);
- ``no lens``: ``intrinsics`` given exactly but not the ``distortion`` (a focal length known
  from a calibration or a spec sheet, the lens taken for a pinhole);
- ``given``: ``intrinsics`` and ``distortion`` given exactly (what the calibration stands for).

It prints per arm and elevation band: the answers within 5 %/2° and 2 %/1°, the median fov
error and the share within 2 %, the median wall time and renders, and how many were confirmed
(and confirmed while outside 5 %/2°).
"""

from __future__ import annotations

import argparse
import asyncio
import io
import math
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import aiohttp
import cv2
import numpy as np
from PIL import ExifTags, Image

from benchmarks.drone_photos import Outcome, answer_estimate, header, print_bands
from cosmos.bench.free_targets.draw import FreeTarget, draw_targets
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import pose_error
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.runner import post_and_follow
from cosmos.bench.variants import dji_xmp
from cosmos.stack import local_stack
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.geometry.camera import film_camera, fov_deg_of
from services.common.geometry.free_camera import (
    FreeCamera,
    LensDistortion,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.lens import invertible_over_film

ARMS: Final = ("calibration", "EXIF only", "nothing read", "no lens", "given")
FOV_RANGE: Final = (1.3, 1.8)
TARGET_SPP: Final = 16
GIMBAL_SIGMA_DEG: Final = 0.5
"""The gimbal's error in pitch and roll (a stabilised gimbal's attitude is good to about that)."""
FULL_FRAME_DIAGONAL_MM: Final = math.hypot(36.0, 24.0)


@dataclass(frozen=True)
class LensPhoto:
    """One drone photo: the JPEG with its XMP, the same without it, the true camera (pixels of
    the photo) and its elevation band."""

    scene: str
    with_xmp: bytes
    exif_only: bytes
    camera: FreeCamera
    fov_deg: float
    band: str
    radius: float


def drone_lens(
    rng: np.random.Generator, width: int, height: int, fov_deg: float
) -> tuple[float, tuple[float, float], LensDistortion]:
    """A wide drone lens for a ``width`` x ``height`` film of horizontal ``fov_deg`` (module
    docstring): its focal length in pixels, principal point and distortion, its radial terms
    shrunk while it would fold the film or have no inverse over it."""
    focal = width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    centre = (
        width * (0.5 + float(rng.uniform(-0.01, 0.01))),
        height * (0.5 + float(rng.uniform(-0.01, 0.01))),
    )
    k1, k2, k3 = rng.uniform(-0.25, -0.05), rng.uniform(0.0, 0.1), rng.uniform(-0.04, 0.0)
    p1, p2 = rng.uniform(-5e-4, 5e-4, size=2)
    film = film_camera(width, height, (focal, focal), centre)
    while True:
        lens = LensDistortion.of_coefficients([float(v) for v in (k1, k2, p1, p2, k3)])
        if invertible_over_film(film, lens):
            return focal, centre, lens
        k1, k2, k3 = 0.8 * k1, 0.8 * k2, 0.8 * k3


def _gimbal(camera: FreeCamera, rng: np.random.Generator) -> tuple[float, float]:
    """The camera's pitch and roll as its gimbal states them: off by :data:`GIMBAL_SIGMA_DEG`."""
    _, pitch, roll = yaw_pitch_roll_of_rotation(camera.rotation())
    off = rng.normal(0.0, GIMBAL_SIGMA_DEG, size=2)
    return float(np.clip(pitch + off[0], -90.0, 90.0)), float(roll + off[1])


def _jpeg(bgr: np.ndarray, focal_35mm: int, xmp: bytes | None) -> bytes:
    exif = Image.Exif()
    tags = exif.get_ifd(ExifTags.IFD.Exif)
    tags[ExifTags.Base.FocalLengthIn35mmFilm] = focal_35mm
    tags[ExifTags.Base.ExifImageWidth] = bgr.shape[1]
    tags[ExifTags.Base.ExifImageHeight] = bgr.shape[0]
    out = io.BytesIO()
    extra = {} if xmp is None else {"xmp": xmp}
    rgb = Image.fromarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    rgb.save(out, "JPEG", quality=92, exif=exif, **extra)
    return out.getvalue()


def _photo(
    renderer: LocalRenderer,
    target: FreeTarget,
    seed: int,
    film_widths: tuple[int, int],
    radius: float,
) -> LensPhoto:
    """``target`` through a drawn drone lens, rendered and enlarged to ``film_widths`` (render,
    photo), as the module docstring says; ``radius`` is its scene's."""
    render_width, photo_width = film_widths
    film = target.annotations.camera
    height = round(render_width * film.height / film.width)
    rng = np.random.default_rng([seed, target.index, 7])
    focal, centre, lens = drone_lens(rng, render_width, height, film.fov_deg)
    camera = target.camera.model_copy(
        update={"fov_deg": None, "fx_px": focal, "fy_px": focal}
        | {"cx_px": centre[0], "cy_px": centre[1], "distortion": lens}
    )
    request = RenderRequest(
        scene=target.scene,
        camera=camera,
        width=render_width,
        height=height,
        spp=TARGET_SPP,
        seed=target.index,
    )
    bgr = cv2.imdecode(np.frombuffer(renderer.render_png(request), np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the renderer's PNG does not decode")
    s = photo_width / render_width
    size = (photo_width, round(height * s))
    big = cv2.resize(bgr, size, interpolation=cv2.INTER_CUBIC)
    # cv2.resize maps a point p of the film (pixel corners at integers) to s p
    f, c = s * focal, (s * centre[0], s * centre[1])
    at_size = camera.model_copy(update={"fx_px": f, "fy_px": f, "cx_px": c[0], "cy_px": c[1]})
    f35 = round(f * FULL_FRAME_DIAGONAL_MM / math.hypot(*size))
    return LensPhoto(
        target.scene,
        _jpeg(big, f35, dji_xmp((f, f), c, size, lens, attitude=_gimbal(camera, rng))),
        _jpeg(big, f35, None),
        at_size,
        fov_deg_of(f, size[0]),
        target.band,
        radius,
    )


def photos(
    scenes: Sequence[str], seeds: Sequence[int], n: int, render_width: int, photo_width: int
) -> list[LensPhoto]:
    """The targets of the module docstring."""
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    made = []
    with LocalRenderer(catalog) as renderer:
        for name in scenes:
            scene = catalog.get(name)
            shapes = scene_shapes(scene)
            radius = scene.spec.camera.radius
            for seed in seeds:
                for target in draw_targets(renderer, scene, shapes, n, seed, fov_range=FOV_RANGE):
                    widths = (render_width, photo_width)
                    made.append(_photo(renderer, target, seed, widths, radius))
    return made


def _query(photo: LensPhoto, arm: str, renders: int = 5) -> tuple[bytes, dict[str, str]]:
    query = {"scene": photo.scene, "mode": "free", "max_iterations": str(renders)}
    if arm == "nothing read":
        query["exif"] = "false"
    if arm in ("no lens", "given"):
        c = photo.camera
        query["intrinsics"] = ",".join(repr(v) for v in (c.fx_px, c.fy_px, c.cx_px, c.cy_px))
    if arm == "given":
        d = photo.camera.distortion or LensDistortion()
        query["distortion"] = ",".join(repr(float(v)) for v in d.coefficients())
    return (photo.exif_only if arm == "EXIF only" else photo.with_xmp), query


async def _search(
    url: str, key: str, shots: Sequence[LensPhoto], arms: Sequence[str], renders: int
) -> dict[str, list[Outcome]]:
    outcomes: dict[str, list[Outcome]] = {arm: [] for arm in arms}
    async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {key}"}) as http:
        for photo in shots:
            truth = Estimate(
                photo.camera.rotation(),
                np.asarray(photo.camera.position, dtype=np.float64),
                photo.fov_deg,
            )
            for arm in arms:
                image, query = _query(photo, arm, renders)
                raw, wall_ms = await post_and_follow(http, url, image, query)
                result = raw.get("result") or {}
                outcomes[arm].append(
                    Outcome(
                        photo.band,
                        arm in ("no lens", "given"),
                        pose_error(answer_estimate(raw), truth, photo.radius),
                        wall_ms,
                        int(result.get("renders") or 0),
                        bool(result.get("confirmed")),
                    )
                )
    return outcomes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="demo,garden")
    parser.add_argument("--seeds", default="11")
    parser.add_argument("--n", type=int, default=8, help="targets per scene and seed")
    parser.add_argument("--render-width", type=int, default=1280)
    parser.add_argument("--photo-width", type=int, default=4000)
    parser.add_argument("--arms", default=",".join(ARMS), help="comma-separated, of ARMS")
    parser.add_argument("--max-iterations", type=int, default=5, help="renders per search")
    args = parser.parse_args(argv)
    arms = [arm.strip() for arm in args.arms.split(",")]
    if unknown := [arm for arm in arms if arm not in ARMS]:
        parser.error(f"unknown arm(s) {', '.join(unknown)}: of {', '.join(ARMS)}")
    seeds = [int(s) for s in args.seeds.split(",")]
    scenes = args.scenes.split(",")
    shots = photos(scenes, seeds, args.n, args.render_width, args.photo_width)
    print(f"{len(shots)} photos {args.photo_width} px wide of {args.scenes}, seeds {args.seeds}")
    with tempfile.TemporaryDirectory(prefix="cosmos-lens-") as tmp:
        with local_stack(Path(tmp)) as stack:
            assert stack.api_key is not None
            search = _search(stack.controller, stack.api_key, shots, arms, args.max_iterations)
            outcomes = asyncio.run(search)
    print(header("arm / band"))
    for arm, mine in outcomes.items():
        print_bands(arm, mine)


if __name__ == "__main__":
    main()
