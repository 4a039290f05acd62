"""Could the search's one render check a focal length stated by the photo's EXIF?

Run: ``.venv/bin/python -m benchmarks.exif_check [--n 16] [--seeds 31,32] [--random-scenes 2]``

An answer whose focal length came from the EXIF is never confirmed: a wrong one moves the
camera along its axis, and the render at the pose agrees all the same
(:mod:`services.controller.free_loop`). The dense fit could check it, by fitting the focal
length from that same render as a search without intrinsics does. This measures whether such a
check tells a right EXIF from a wrong one.

Targets: free targets (``cosmos.bench.free_targets``' draw) of the demo scene and of
``--random-scenes`` generated scenes per seed, their clean images, the box detections their
exact visible boxes with the detector's edge noise (:func:`~cosmos.bench.free_targets.solver.
target_detections`). Each is searched as if its EXIF stated the true focal length times
``1 + e`` for each ``e`` of :data:`EXIF_ERRORS` (±2 % is a 35 mm equivalent rounded to the
millimetre at 24 mm; 5 % and 15 % a crop or digital zoom the EXIF does not say): the box solve
with that focal length, one render at its pose on the target's film (as a search with known
intrinsics renders), then from that render

* the dense fit of the pose alone, with the stated focal length: the answer, as now;
* the dense fit of the pose and the focal length, started from the stated one alone
  (:data:`~services.optimizer.refine_pose.CHECK_ZOOMS`), as the optimizer checks it: the check.

It prints per ``e`` and elevation band the answers within 5 %/2°, the check's focal length
against the truth and against the EXIF (median), and what two rules would have done:

* **confirm** when the check lands within :data:`AGREE` of the stated focal length with a
  standard deviation at most :data:`SIGMA`, both fits leaving :data:`SHARE` of their edge
  points on the target's: how many answers that confirms, and how many of those are wrong;
* **switch** to the check's pose (its focal length estimated) when it lands more than
  :data:`DISAGREE` from the stated one at that standard deviation (in brackets, at
  :data:`LOOSE_SIGMA`), leaving :data:`SHARE` of its edge points on the target's: the answers
  within 5 %/2° before and after.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from cosmos.bench.free_targets.dense import render_at
from cosmos.bench.free_targets.draw import BANDS, FreeTarget, draw_targets
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import pose_error
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solver import target_detections
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.optimizer.free import DenseFit, refine_dense, scene_objects
from services.optimizer.free.edges import outline
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.solve import solve_free_pose
from services.optimizer.refine_pose import CHECK_ZOOMS
from services.renderer.settings import RendererSettings

EXIF_ERRORS: Final = (-0.05, -0.02, 0.0, 0.02, 0.05, 0.15)
"""The stated focal length's error, as a share of the true one."""
VIEW_SPP: Final = 16
AGREE: Final = 0.02
DISAGREE: Final = 0.03
SIGMA: Final = 0.005
LOOSE_SIGMA: Final = 0.01
"""The switch again with this standard deviation (in brackets)."""
SHARE: Final = 0.9
WITHIN: Final = (0.05, 2.0)


@dataclass(frozen=True)
class Case:
    """One target searched with one stated focal length: its band, the error ``e``, whether
    the answer (pose alone) and the check's pose are within 5 %/2°, and the check."""

    band: str
    error: float
    answer_right: bool
    check_right: bool
    answer_share: float
    check_share: float
    check_sigma: float
    check_vs_stated: float
    check_vs_true: float

    def confirms(self) -> bool:
        return (
            self.answer_share >= SHARE
            and self.check_share >= SHARE
            and self.check_sigma <= SIGMA
            and abs(self.check_vs_stated) <= AGREE
        )

    def switches(self, sigma: float = SIGMA) -> bool:
        return (
            self.check_share >= SHARE
            and self.check_sigma <= sigma
            and abs(self.check_vs_stated) > DISAGREE
        )


def _gray(png: bytes) -> np.ndarray:
    gray = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise ValueError("the renderer's PNG does not decode")
    return np.asarray(gray)


def _estimate(fit: DenseFit, width: int) -> Estimate:
    return Estimate.of_world_to_camera(fit.rotation, fit.translation, fit.intrinsics.fov_deg(width))


def _cases(
    renderer: LocalRenderer, catalog: SceneCatalog, target: FreeTarget, seed: int
) -> Iterator[Case]:
    """``target`` searched with each stated focal length of :data:`EXIF_ERRORS`."""
    scene = catalog.get(target.scene)
    objects = scene_objects(scene.spec, scene.assets)
    radius = scene.spec.camera.radius
    film = target.annotations.camera
    truth = Estimate.of_world_to_camera(
        np.asarray(film.rotation), np.asarray(film.translation), film.fov_deg
    )
    detections = target_detections(target, objects, np.random.default_rng([seed, target.index]))
    gray = _gray(target.png)
    for error in EXIF_ERRORS:
        stated = Intrinsics(film.fx * (1 + error), film.fy * (1 + error), film.cx, film.cy)
        answer = solve_free_pose(objects, detections, film.width, film.height, stated)
        if answer.pose is None:
            continue
        rendered = render_at(renderer, target, answer.pose.free_camera(), VIEW_SPP)
        if rendered is None:
            continue
        rgb, geometry, pinhole = rendered
        near = None
        if geometry.shading is not None:
            near = outline(geometry.depth, geometry.objects, geometry.shading)
        fits = [
            refine_dense(
                gray,
                rgb,
                geometry.depth,
                pinhole,
                fit_focal=focal,
                near=near,
                focal_reference=stated.fx,
                zooms=CHECK_ZOOMS,
            )
            for focal in (False, True)
        ]
        right = [
            pose_error(_estimate(fit, film.width), truth, radius).within(*WITHIN) for fit in fits
        ]
        check = fits[1]
        # a focal length the edges left loose checks nothing either way
        sigma = check.focal_sigma if check.focal_fitted else math.inf
        yield Case(
            band=target.band,
            error=error,
            answer_right=right[0],
            check_right=right[1],
            answer_share=fits[0].share(),
            check_share=check.share(),
            check_sigma=sigma,
            check_vs_stated=check.intrinsics.fx / stated.fx - 1.0,
            check_vs_true=check.intrinsics.fx / film.fx - 1.0,
        )


def _print(cases: list[Case]) -> None:
    print(
        f"{'EXIF':>6s} {'band':6s} {'n':>3s} {'answer ok':>9s}  {'check−true':>10s} "
        f"{'check−EXIF':>10s}  {'confirmed (wrong)':>17s}  ok before → switched (at σ 1 %)"
    )
    groups: dict[tuple[float, str], list[Case]] = defaultdict(list)
    for case in cases:
        groups[(case.error, case.band)].append(case)
        groups[(case.error, "all")].append(case)
    for error in EXIF_ERRORS:
        for band in (*BANDS, "all"):
            group = groups.get((error, band))
            if not group:
                continue
            confirmed = [c for c in group if c.confirms()]
            after, loose = (
                sum(c.check_right if c.switches(sigma) else c.answer_right for c in group)
                for sigma in (SIGMA, LOOSE_SIGMA)
            )
            print(
                f"{error:+6.0%} {band:6s} {len(group):3d} "
                f"{sum(c.answer_right for c in group):9d}  "
                f"{np.median([c.check_vs_true for c in group]):+10.1%} "
                f"{np.median([c.check_vs_stated for c in group]):+10.1%}  "
                f"{len(confirmed):9d} ({sum(not c.answer_right for c in confirmed):d})    "
                f"{sum(c.answer_right for c in group):14d} → {after:d} ({loose:d})"
            )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=16, help="targets per scene")
    parser.add_argument("--seeds", default="31,32")
    parser.add_argument("--random-scenes", type=int, default=2)
    args = parser.parse_args(argv)
    cases: list[Case] = []
    settings = RendererSettings()
    with tempfile.TemporaryDirectory() as work:
        for seed in (int(s) for s in args.seeds.split(",")):
            ids = ["demo"]
            for i in range(args.random_scenes):
                ids.append(f"rand{seed}-{i}")
                generate_scene(np.random.default_rng([seed, i]), Path(work), ids[-1])
            catalog = SceneCatalog([*settings.scene_directories(), Path(work)])
            with LocalRenderer(catalog, settings) as renderer:
                for scene_id in ids:
                    scene = catalog.get(scene_id)
                    for target in draw_targets(renderer, scene, scene_shapes(scene), args.n, seed):
                        cases.extend(_cases(renderer, catalog, target, seed))
    _print(cases)


if __name__ == "__main__":
    main()
