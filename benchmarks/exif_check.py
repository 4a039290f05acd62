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
  :data:`LOOSE_SIGMA`, and with the check started from every zoom of
  :data:`~services.optimizer.free.dense.ZOOM_STARTS`, as a fit without intrinsics is),
  leaving :data:`SHARE` of its edge points on the target's: the answers within 5 %/2° before
  and after.

Last, the median milliseconds per fit: the pose alone, the check, the check from every zoom.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

import numpy as np

from benchmarks.seeded import seeded_scenes
from cosmos.bench.free_targets.dense import decode_gray, fit_estimate, near_outline, render_at
from cosmos.bench.free_targets.draw import BANDS, FreeTarget, draw_targets
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import pose_error
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solver import target_detections
from services.common.catalog import SceneCatalog
from services.common.depth_archive import DepthImage
from services.common.geometry.camera import PinholeCamera
from services.optimizer.free import DenseFit, refine_dense, scene_objects
from services.optimizer.free.dense import ZOOM_STARTS
from services.optimizer.free.focal_bounds import FocalRange
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.solve import solve_free_pose
from services.optimizer.refine_pose import CHECK_ZOOMS

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
class Check:
    """A focal-free fit from the render: whether its pose is within 5 %/2°, its share of edge
    points on the target's, its focal length's standard deviation (∞ when not pinned) and
    offsets from the stated and the true one, and its milliseconds."""

    right: bool
    share: float
    sigma: float
    vs_stated: float
    vs_true: float
    ms: float

    def switches(self, sigma: float = SIGMA) -> bool:
        """Whether it overrules the stated focal length at ``sigma``."""
        return self.share >= SHARE and self.sigma <= sigma and abs(self.vs_stated) > DISAGREE


@dataclass(frozen=True)
class Case:
    """One target searched with one stated focal length: its band, the error ``e``, the answer
    (the pose alone: within 5 %/2°, its share, its milliseconds) and the ``checks`` (started
    from :data:`~services.optimizer.refine_pose.CHECK_ZOOMS`, then from every zoom of
    :data:`~services.optimizer.free.dense.ZOOM_STARTS`)."""

    band: str
    error: float
    answer_right: bool
    answer_share: float
    answer_ms: float
    checks: tuple[Check, Check]

    def confirms(self) -> bool:
        check = self.checks[0]
        return (
            self.answer_share >= SHARE
            and check.share >= SHARE
            and check.sigma <= SIGMA
            and abs(check.vs_stated) <= AGREE
        )

    def after(self, k: int, sigma: float = SIGMA) -> bool:
        """Whether the answer is within 5 %/2° once check ``k`` may overrule it."""
        check = self.checks[k]
        return check.right if check.switches(sigma) else self.answer_right


@dataclass(frozen=True)
class Searched:
    """What a search with a stated focal length rendered: the target's grey and truth, the
    stated intrinsics, the render (colours, geometry, pinhole) and its outline pixels."""

    gray: np.ndarray
    truth: Estimate
    radius: float
    stated: Intrinsics
    rendered: tuple[np.ndarray, DepthImage, PinholeCamera]

    def fitted(self, focal: bool, zooms: tuple[float, ...]) -> tuple[DenseFit, float]:
        """The dense fit from the render (the focal length free or not) and its ms."""
        rgb, geometry, pinhole = self.rendered
        started = time.perf_counter()
        fit = refine_dense(
            self.gray,
            rgb,
            geometry.depth,
            pinhole,
            fit_focal=focal,
            near=near_outline(geometry),
            focal_range=FocalRange.about(self.stated.fx),
            zooms=zooms,
        )
        return fit, (time.perf_counter() - started) * 1000.0

    def right(self, fit: DenseFit) -> bool:
        width = self.rendered[2].width
        return pose_error(fit_estimate(fit, width), self.truth, self.radius).within(*WITHIN)

    def check(self, zooms: tuple[float, ...], true_fx: float) -> Check:
        fit, ms = self.fitted(True, zooms)
        return Check(
            right=self.right(fit),
            share=fit.share(),
            # a focal length the edges left loose checks nothing either way
            sigma=fit.focal_sigma if fit.focal_fitted else math.inf,
            vs_stated=fit.intrinsics.fx / self.stated.fx - 1.0,
            vs_true=fit.intrinsics.fx / true_fx - 1.0,
            ms=ms,
        )


def _cases(
    renderer: LocalRenderer, catalog: SceneCatalog, target: FreeTarget, seed: int
) -> Iterator[Case]:
    """``target`` searched with each stated focal length of :data:`EXIF_ERRORS`."""
    scene = catalog.get(target.scene)
    objects = scene_objects(scene.spec, scene.assets)
    film = target.annotations.camera
    truth = Estimate.of_world_to_camera(
        np.asarray(film.rotation), np.asarray(film.translation), film.fov_deg
    )
    detections = target_detections(target, objects, np.random.default_rng([seed, target.index]))
    gray = decode_gray(target.png)
    for error in EXIF_ERRORS:
        stated = Intrinsics(film.fx * (1 + error), film.fy * (1 + error), film.cx, film.cy)
        answer = solve_free_pose(objects, detections, film.width, film.height, stated)
        if answer.pose is None:
            continue
        rendered = render_at(renderer, target, answer.pose.free_camera(), VIEW_SPP)
        if rendered is None:
            continue
        searched = Searched(gray, truth, scene.spec.camera.radius, stated, rendered)
        answer_fit, answer_ms = searched.fitted(False, CHECK_ZOOMS)
        yield Case(
            band=target.band,
            error=error,
            answer_right=searched.right(answer_fit),
            answer_share=answer_fit.share(),
            answer_ms=answer_ms,
            checks=(
                searched.check(CHECK_ZOOMS, film.fx),
                searched.check(ZOOM_STARTS, film.fx),
            ),
        )


def _print(cases: list[Case]) -> None:
    print(
        f"{'EXIF':>6s} {'band':6s} {'n':>3s} {'answer ok':>9s}  {'check−true':>10s} "
        f"{'check−EXIF':>10s}  {'confirmed (wrong)':>17s}  ok before → switched (at σ 1 %; "
        "from every zoom)"
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
            after, loose, every = (
                sum(c.after(k, sigma) for c in group)
                for k, sigma in ((0, SIGMA), (0, LOOSE_SIGMA), (1, SIGMA))
            )
            print(
                f"{error:+6.0%} {band:6s} {len(group):3d} "
                f"{sum(c.answer_right for c in group):9d}  "
                f"{np.median([c.checks[0].vs_true for c in group]):+10.1%} "
                f"{np.median([c.checks[0].vs_stated for c in group]):+10.1%}  "
                f"{len(confirmed):9d} ({sum(not c.answer_right for c in confirmed):d})    "
                f"{sum(c.answer_right for c in group):14d} → {after:d} ({loose:d}; {every:d})"
            )
    alone = float(np.median([c.answer_ms for c in cases]))
    one, all_zooms = (float(np.median([c.checks[k].ms for c in cases])) for k in (0, 1))
    print(
        f"ms per fit (median): the pose alone {alone:.0f}, the check {one:.0f} "
        f"({one / alone:.1f} x), from every zoom {all_zooms:.0f} ({all_zooms / alone:.1f} x)"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=16, help="targets per scene")
    parser.add_argument("--seeds", default="31,32")
    parser.add_argument("--random-scenes", type=int, default=2)
    args = parser.parse_args(argv)
    cases: list[Case] = []
    seeds = (int(s) for s in args.seeds.split(","))
    for renderer, catalog, scene_id, seed in seeded_scenes(seeds, args.random_scenes):
        scene = catalog.get(scene_id)
        for target in draw_targets(renderer, scene, scene_shapes(scene), args.n, seed):
            cases.extend(_cases(renderer, catalog, target, seed))
    _print(cases)


if __name__ == "__main__":
    main()
