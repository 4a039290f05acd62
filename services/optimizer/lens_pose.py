"""The dense fit's lens check (:mod:`services.optimizer.free.lens_check`) in the contract's
terms: whether the target's edges bend as a distorting lens's (``LensBend``), and the pose
fitted through that lens (``RefinePoseResponse.lens_pose``).

Unless the pose states a lens, the fit is done once more at full resolution from where it
ended with OpenCV's radial ``k1`` free, and the focal length too unless it was given (fitted,
or stated by the photo's EXIF, whose error a radial term would otherwise absorb: a pinhole
photo whose EXIF states a focal length 15 % long bent so)
(:func:`~services.optimizer.free.lens_check.radial_check`, ~8 ms): a photo taken through a
distorting lens, fitted as a pinhole's, may still agree with its render box by box while
several percent off. On an accepted fit, its edges are said to bend (``LensBend.bends``)
when ``k1`` moves the farthest explained points by at least :data:`BEND_PX` pixels of the
fit and lies at least :data:`BEND_Z` of its standard deviations from 0; the answer then
carries the pose fitted with that ``k1`` (``lens_pose``), and the controller never
confirms it (:mod:`services.controller.lens_check`, with what that did to the answers).

Measured on targets rendered as pinholes: 124 fits without the fov of ``python -m
cosmos.bench.free_targets`` (``--scene demo --random-scenes 2 --n 8 --seed 1`` and ``--scene
demo --scene garden --random-scenes 3 --n 12 --seed 2``, the in-process dense stage with the
check on; clean, JPEG and noise) bent at most 1.5 pixels of the fit (``k1`` −0.019, 8 σ).
Through the stack (``cosmos bench --free --scene demo --scene garden --random-scenes 2 --n 8
--seed 41 --onboard none``, 160 searches, one run), 6 accepted fits bent (2.6–5.1 px at
5–27 σ: two under another light, four of one generated scene's view without the fov seen by
the general model), all of answers already ambiguous; no answer changed its status or its
share within 5 %/2° or 2 %/1° against the same run without the check (78 and 70 of 160,
49 confirmed, none wrong). On ``benchmarks.drone_lens``' 32 photos of barrel lenses (``k1``
−0.21…−0.06) searched with nothing read, 31 fits bent by 2.5–30 pixels of the fit at 8–137
σ (the other fitted ``k1`` +0.007); searched with the focal length given and not the lens,
a pose 8 % of the radius and 6.6° off was confirmed, its check bending 5.8 pixels at 4.3 σ.

A moved light's shadow edges can bend the check of a pinhole photo too, and at 320 pixels
neither the bend nor its σ tells them from a lens: five ``photo`` targets of ``cosmos bench
--free`` (seeds 41, 43, 44) bent 3–5 px at 4.6–8.6 σ, where ``benchmarks.drone_lens``' photos
brought to 320 px bent from 2.5 px at 5.5 σ. What the lens explains does better: its ``k1``
removed 0.7–5.9 % of the pinhole fit's robust edge cost (``LensBend.cost_drop``) on those
targets, and at most 2.8 % on 48 draws of the same kind (three views, eight lights, with and
without the photo finish: ``tests/optimizer/test_dense.py`` keeps one), against 3.8 % and up
(median 42 %) on the 84 drone-lens searches at 320 px whose check bent. So a bend whose ``k1``
removes less than :data:`LENS_POSE_DROP` makes no lens pose: the answer keeps the pinhole's fit,
never confirmed either way. Measured: the 40 ``photo`` and ``changed`` searches of seed 41 on
demo and garden, 33 → 34 within 5 %/2° (a view 3.9 %/2.4° off came to 2.0 %/1.1°, one render
fewer); of the 96 drone-lens searches at 320 px none moved, at 4000 px one (0.1 % → 0.5 %).
At 6.5 % three of those answers gained, but four drone answers at 320 px moved 1–3 % away (two
fewer within 2 %/1°): not taken.
"""

from __future__ import annotations

import math
from typing import Final

from pydantic import ValidationError

from services.common.contracts.free import DenseReport, FreePose, LensBend
from services.common.geometry.free_camera import (
    LensDistortion,
    free_pinhole_camera,
)
from services.common.geometry.lens import invertible_over_film
from services.optimizer.free.lens_check import RadialCheck
from services.optimizer.free.objects import SceneObjects
from services.optimizer.free_pose import predicted_boxes

__all__ = ["BEND_PX", "BEND_Z", "LENS_POSE_DROP", "lens_bend", "lens_explains", "lens_pose"]

BEND_PX: Final = 2.0
"""The lens check's bend (``LensBend.bend_px``, in pixels of the fit: the coarser of the film's
and the target's) from which the target's edges are taken to bend as a distorting lens's…"""
BEND_Z: Final = 4.0
"""…when its ``k1`` is also this many of its standard deviations from 0 (and not on a bound of
:data:`~services.optimizer.free.level_fit.RADIAL_RANGE`)."""
LENS_POSE_DROP: Final = 0.035
"""A bend whose ``k1`` fit removes less than this share of the pinhole fit's robust edge cost
(``LensBend.cost_drop``) leaves the answer at the pinhole's pose, still never confirmed: see
the module docstring for what set it."""


def lens_bend(check: RadialCheck | None, scale: float, accepted: bool) -> LensBend | None:
    """A fit's lens ``check`` in the contract's terms (module docstring), its bend in target
    pixels (the film is ``scale`` times the target), judged only when the fit was ``accepted``
    (one that was not leaves the box pose, and its check says nothing of the lens); None
    without one, or when its spread is not finite."""
    if check is None or not math.isfinite(check.sigma) or not math.isfinite(check.bend_px):
        return None
    fit_pixels = check.bend_px / max(scale, 1.0)  # the coarser of the film's and target's
    bends = fit_pixels >= BEND_PX and abs(check.k1) >= BEND_Z * check.sigma
    bends = bends and accepted and not check.bounded
    return LensBend(
        k1=check.k1,
        k1_sigma=check.sigma,
        bend_px=check.bend_px / scale,
        inliers=check.inliers,
        bends=bends,
        cost_drop=check.cost_drop,
    )


def lens_explains(check: RadialCheck) -> bool:
    """Whether a bending check's lens is worth its pose: it removes at least
    :data:`LENS_POSE_DROP` of the pinhole fit's robust cost (a check started through a lens,
    with no pinhole fit to compare with, is taken at its word)."""
    return check.cost_drop is None or check.cost_drop >= LENS_POSE_DROP


def lens_pose(
    check: RadialCheck,
    start: FreePose,
    report: DenseReport,
    film: tuple[int, int],
    objects: SceneObjects,
) -> FreePose | None:
    """``start`` moved to the lens check's fit, its intrinsics (target pixels) ``estimated``
    with the fitted ``k1`` as the lens, and its pairs' boxes predicted through it; None when
    that lens explains too little of the pinhole fit's misfit (:func:`lens_explains`) or would
    fold the film's corners (the fit's ``k1`` is then no lens)."""
    if not lens_explains(check):
        return None
    k = start.intrinsics
    fx, fy = k.fx_px * check.zoom, k.fy_px * check.zoom
    width, height = film
    try:
        lens = LensDistortion(k1=check.k1)
        intrinsics = k.refocused(fx, fy, width, "estimated", lens)
        camera_to_world = check.rotation.T
        position = (float(check.position[0]), float(check.position[1]), float(check.position[2]))
        names = [c.object for c in start.correspondences]
        focal = (fx, fy, k.cx_px, k.cy_px)
        boxes = predicted_boxes(objects, names, camera_to_world, position, focal, lens)
        residual = report.residual_px if report.residual_px is not None else 0.0
        pairs = tuple(
            c.model_copy(update={"predicted_box": boxes[c.object]}) for c in start.correspondences
        )
        pose = start.moved_to(camera_to_world, position, intrinsics, residual).model_copy(
            update={"correspondences": pairs}
        )
        pinhole = free_pinhole_camera(pose.camera(), width, height, intrinsics.fov_deg)
    except (ValidationError, ValueError):
        return None
    return pose if invertible_over_film(pinhole, lens) else None
