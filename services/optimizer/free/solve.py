"""The 6-DoF camera pose from the target's boxes alone, before any render, and how sure it is.

The steps (each in its module):

1. hypotheses from minimal sets of box centres, over the label-compatible assignments
   (:mod:`.hypotheses`; an own-detector label contradicted by the detection's colour also
   allows the object its colour names: :mod:`.colours`);
2. for each distinct hypothesis, its edge fits (:mod:`.hypothesis_fits`): PnP on the paired
   centres corrected for the box-centre bias, then least squares on the box edges
   (:mod:`.refine`); the pairs are then re-drawn at the refined pose with a box-edge gate
   (:func:`inlier_gate`) and the edges refitted on them; the best fit is also refitted
   without each of its loose pairs in turn (:func:`~.hypothesis_fits.left_out`: a moved
   object's box); the fits are ranked by :func:`truncated_cost` over all detections, not by
   pairs first;
3. without given intrinsics and with at least :data:`~.hypothesis_fits.MIN_FOCAL_PAIRS` pairs,
   the focal length joins every hypothesis' edge fit (:mod:`.hypothesis_fits`), within the
   lenses considered (:class:`~.focal_bounds.FocalRange`). With fewer pairs, or a fit that
   ends on a bound, the scene camera's field of view is used and the answer says so;
4. with the camera's attitude the photo states (a drone's gimbal pitch and roll), the fits whose
   down direction lies more than :data:`ATTITUDE_TOLERANCE_DEG` from it are dropped before any
   is ranked as the answer or a rival (none left: ``ambiguous``, ``attitude``);
5. the answer's status (:class:`FreePoseAnswer`).

With fewer than three usable detections no minimal set exists: the edges are fitted from a ring
of start views around the scene (:data:`~.few.FEW_STARTS_DEG`), and the answer is ``ambiguous`` with
the distinct fits as alternatives, never ``found``.

Status
------
``found``
    The best pose (least :func:`truncated_cost`) pairs at least four detections, or three
    when it is clearly unique: no distinct pose (:func:`~.hypotheses.distinct`) pairs as many
    detections with an edge RMS within :data:`UNIQUE_RATIO_3` (three pairs) or
    :data:`AMBIGUITY_RATIO` (four or more) times ``max(best RMS, NOISE_FLOOR_PX)``.
``ambiguous``
    Fewer than three pairs, or such a distinct pose exists (a symmetric layout, look-alikes
    that can swap): the best pose and the alternatives, with their residuals. Also a pose the
    boxes pin only loosely, which is never ``found``:

    * without given intrinsics and too few pairs to fit the focal, the scene camera's field of
      view is assumed, and distance trades against focal length along the view axis;
    * its own uncertainty reaches a wrong answer: ``FIRM_SIGMAS · σ_position > WRONG_POSITION ·
      r`` or ``FIRM_SIGMAS · σ_rotation > WRONG_ROTATION_DEG`` (``r`` the scene radius). σ takes
      the edge noise at ``max(NOISE_FLOOR_PX, edge RMS)``: boxes that fit worse than the
      detector's noise are off by more than it (the general model's on shapes it never saw: one
      9 px off pulled a six-pair fit 16 % / 12° away at 4.1 px RMS, which the floor called
      found; an object moved since the scene was modelled: a nadir view of five equal balls
      fitted a pose 20 % / 11° off at 1.0 px, found at the floor).
      Measured on free targets of generated scenes (``python -m cosmos.bench.free_targets
      --random-scenes 4``), the error over σ reached about 2 in one answer in ten, and a third of
      ``found`` answers off by more than 10 % / 5° had no given intrinsics.
``failed``
    No usable detection: none, none confident enough, or none whose label names an object of
    the scene.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import (
    attitude_error_deg,
    quaternion_of_rotation,
    rotation_of_quaternion,
    yaw_pitch_roll_of_rotation,
)
from services.optimizer.free.answer import (
    Ambiguity,
    Correspondence,
    FreePoseAnswer,
    IntrinsicsSource,
    IntrinsicsUsed,
    KnownSource,
    PoseCandidate,
)
from services.optimizer.free.colours import recoloured
from services.optimizer.free.few import few_detections, few_fits
from services.optimizer.free.focal_bounds import FocalRange
from services.optimizer.free.hypotheses import (
    distinct,
    general_labels,
    hypotheses,
    label_costs,
)
from services.optimizer.free.hypothesis_fits import (
    MIN_FOCAL_PAIRS,
    EdgeFits,
    Fit,
    focal_fits,
    left_out,
    refined,
)
from services.optimizer.free.objects import SceneObjects
from services.optimizer.free.refine import Intrinsics, pose_uncertainty
from services.optimizer.free.tolerances import (
    NOISE_FLOOR_PX,
    inlier_gate,
    truncated_cost,
)
from services.optimizer.geometry import FloatArray
from services.optimizer.mapping import clipped_sides

__all__ = [
    "AMBIGUITY_RATIO",
    "solve_free_pose",
]

AMBIGUITY_RATIO: Final = 2.0
WRONG_POSITION: Final = 0.10
"""A position error (fraction of the scene radius) past which an answer is wrong."""
WRONG_ROTATION_DEG: Final = 5.0
"""A rotation error past which an answer is wrong."""
FIRM_SIGMAS: Final = 3.0
"""How many standard deviations of its own uncertainty a ``found`` pose keeps inside
:data:`WRONG_POSITION` and :data:`WRONG_ROTATION_DEG`."""
UNIQUE_RATIO_3: Final = 3.0
REFINED_HYPOTHESES: Final = 6
"""The best hypotheses refined. The others (up to :func:`~.hypotheses.hypotheses`' eight) are
refined too when every refined fit pairs fewer than three detections: a box whose object has
moved can lead every hypothesis that pairs it into the other basin of a flip, where the pairs
re-drawn shrink to two. Seen on a demo view at 10–30° (``cosmos bench --free --scene demo
--scene garden --n 6 --seed 43 --target-width 1280 --fov-range 1.5,2.2``, #5 ``changed``: the
red ball moved 0.97 units, the fov given): the six best hypotheses all paired it, ranked above
the one that did not for pairing five boxes, and came down to two pairs 162 % of the radius
off; the seventh pairs the four others and is refined 0.4 % off."""
MAX_ALTERNATIVES: Final = 4
ATTITUDE_TOLERANCE_DEG: Final = 10.0
"""How far (:func:`~services.common.geometry.free_camera.attitude_error_deg`) a fit's down
direction may lie from the one the photo's attitude states. A box fit within 10 %/5° of the
truth is within 5° of it; a gimbal's attitude is good to about a degree, a modelled site's
ground to a few more. On the ``RESULTS.md`` run's 199 box estimates (``cosmos bench --free
--scene demo --random-scenes 2 --n 8 --seed 21``), the 111 within 10 %/5° of the truth were at
most 4.7° from its down direction; of the 88 outside, 31 were more than 10° from it (flips and
the general model's wrong pairings, 10–134°)."""
OWN_DETECTOR: Final = (
    "a detector of the scene's own objects (`cosmos scenes add`: the general one serving this "
    "scene names shapes, not objects, and misses shapes it never saw)"
)
"""What an ambiguous answer on the general model's detections adds to its advice. On the
generated scenes of ``cosmos bench --free --scene demo --random-scenes 2 --n 8`` (seeds 1-4, the
intrinsics given, clean, JPEG and noise), 14 of the 15 targets with four or more objects in view
that ended ambiguous and outside 5 %/2° paired at most two objects: the model had boxed one to
four of them, and the advice then said to take a wider view."""


def _candidate(
    fit: Fit,
    objects: SceneObjects,
    evidence: tuple[FloatArray, NDArray[np.bool_], tuple[str, ...], NDArray[np.intp]],
    width: float,
) -> PoseCandidate:
    boxes, masks, labels, index = evidence
    sigmas = pose_uncertainty(
        objects.subset(fit.objects),
        boxes[fit.detections],
        masks[fit.detections],
        fit.fit,
        max(NOISE_FLOOR_PX, fit.fit.rms_px),
        with_focal=fit.source == "estimated",
    )
    rotation_cw = fit.fit.rotation().T
    k = fit.fit.intrinsics
    c = fit.fit.position()
    ypr = yaw_pitch_roll_of_rotation(rotation_cw)
    return PoseCandidate(
        position=(float(c[0]), float(c[1]), float(c[2])),
        quaternion_wxyz=quaternion_of_rotation(rotation_cw),
        yaw_pitch_roll_deg=(ypr[0], ypr[1], ypr[2]),
        intrinsics=IntrinsicsUsed(
            fx_px=k.fx,
            fy_px=k.fy,
            cx_px=k.cx,
            cy_px=k.cy,
            fov_deg=k.fov_deg(width),
            source=fit.source,
        ),
        residual_px=fit.fit.rms_px,
        correspondences=tuple(
            Correspondence(
                detection=int(index[d]),
                object=objects.names[o],
                label=labels[d],
                residual_px=float(fit.fit.pair_rms_px[n]),
            )
            for n, (d, o) in enumerate(zip(fit.detections, fit.objects, strict=True))
        ),
        position_sigma=sigmas[0],
        rotation_sigma_deg=sigmas[1],
    )


def _distinct_best(fits: list[Fit], radius: float, gates: FloatArray) -> list[Fit]:
    """The fits, best first (least :func:`truncated_cost`, then most pairs), one of each
    distinct pose."""
    ranked = sorted(
        fits, key=lambda f: (truncated_cost(f.fit, f.detections, gates), -len(f.detections))
    )
    kept: list[Fit] = []
    for f in ranked:
        if all(distinct(f.key, k.key, radius) for k in kept):
            kept.append(f)
    return kept


def solve_free_pose(
    objects: SceneObjects,
    detections: Sequence[Detection],
    width: int,
    height: int,
    intrinsics: Intrinsics | None = None,
    *,
    min_confidence: float = 0.0,
    seed: int = 0,
    pixel_scale: float = 1.0,
    known_from: KnownSource = "given",
    attitude: tuple[float, float] | None = None,
) -> FreePoseAnswer:
    """The camera pose from the target's detections alone (module docstring).

    Parameters
    ----------
    objects : the scene's objects (:func:`.objects.scene_objects`).
    detections : the target's detections, boxes in pixels of its ``width`` x ``height`` image.
    intrinsics : the photo's, when known; otherwise the scene camera's field of view is the start
        and the focal length is estimated from four pairs on.
    min_confidence : detections below it are not used.
    seed : orders the general model's equally priced assignments when there are too many
        minimal sets to solve them all (:mod:`.minimal_sets`).
    pixel_scale : target pixels per pixel of the detector's input
        (:func:`~.tolerances.pixel_scale`). Every pixel tolerance of the solve
        (:data:`~.tolerances.NOISE_FLOOR_PX`, the gates, the edge fit's robust scale, the border
        margin) is one of the detector's, whose box errors grow with the image it shrank: the
        solve runs on the boxes and intrinsics divided by it, and answers in target pixels. The
        same view at 320 and 4000 pixels wide was answered with confidence 0.99 and 0.20 when
        the tolerances were target pixels.
    known_from : where ``intrinsics`` come from: ``given`` by the user, a drone's
        ``calibration`` or the photo's ``exif``; the answer's intrinsics say so. All are used
        alike.
    attitude : the camera's ``(pitch, roll)`` in degrees when the photo states them (its
        gimbal's); fits far from them are not answered (:data:`ATTITUDE_TOLERANCE_DEG`).
    """
    s = pixel_scale
    scaled = [d.model_copy(update={"box": tuple(v / s for v in d.box)}) for d in detections]
    k = intrinsics.on_film(1.0 / s) if intrinsics is not None else None
    answer = _solve(
        objects,
        scaled,
        (width / s, height / s),
        (k, known_from, attitude),
        min_confidence,
        seed,
        s,
    )
    return answer.in_target_pixels(s)


def _solve(
    objects: SceneObjects,
    detections: Sequence[Detection],
    size: tuple[float, float],
    known: tuple[Intrinsics | None, KnownSource, tuple[float, float] | None],
    min_confidence: float,
    seed: int,
    unit: float,
) -> FreePoseAnswer:
    """:func:`solve_free_pose` in the detector's pixels (``size`` the image's in them), with the
    ``known`` intrinsics (None if not), where they come from and the stated attitude (None if
    not); the reasons say pixels times ``unit``, the target's."""
    width, height = size
    intrinsics, known_from, attitude = known
    labels_all = tuple(d.label for d in detections)
    measured = [d.color if d.color is not None else (np.nan,) * 3 for d in detections]
    general_all = general_labels(objects, labels_all)
    costs_all = recoloured(label_costs(objects, labels_all), objects, general_all, measured)
    compatible_all = np.isfinite(costs_all)
    boxes_all = np.array([d.box for d in detections], dtype=np.float64).reshape(-1, 4)
    finite = np.all(np.isfinite(boxes_all), axis=1)
    sized = (boxes_all[:, 2] > boxes_all[:, 0]) & (boxes_all[:, 3] > boxes_all[:, 1])
    confident = np.array([d.confidence >= min_confidence for d in detections], dtype=np.bool_)
    ok = finite & sized & confident & compatible_all.any(axis=1)
    index = np.flatnonzero(ok)
    if len(index) == 0:
        return FreePoseAnswer("failed", _failure(detections, objects, confident), None, (), 0)
    boxes, compatible = boxes_all[index], compatible_all[index]
    labels = tuple(labels_all[i] for i in index)
    masks = clipped_sides(boxes, width, height)
    given = intrinsics is not None
    k0 = intrinsics if intrinsics is not None else Intrinsics.of_fov(objects.fov_deg, width, height)
    scores = np.array([detections[int(i)].confidence for i in index])
    general = bool(general_labels(objects, labels).any())
    hyps = hypotheses(
        objects,
        boxes,
        costs_all[index],
        k0,
        width,
        height,
        confidence=scores,
        general=general,
        seed=seed,
    )
    starts = [(h.rvec, h.tvec, h.detections, h.objects) for h in hyps]
    fits: list[Fit] = []

    def keep(fit: Fit | None) -> None:
        """``fit`` among the fits, when it stands above the ground; its intrinsics' source."""
        if fit is not None and fit.fit.position()[2] > 0.0:
            fits.append(fit if not given else Fit(fit.fit, fit.detections, fit.objects, known_from))

    lenses = FocalRange.of(k0.fx, width, height)
    edge_fits = EdgeFits(objects, boxes, masks, focal_range=lenses)
    for batch in (starts[:REFINED_HYPOTHESES], starts[REFINED_HYPOTHESES:]):
        if any(len(f.detections) >= 3 for f in fits):
            break  # the rest only when every refined fit collapsed (:data:`REFINED_HYPOTHESES`)
        firsts = focal_fits(edge_fits, batch, k0, not given)
        for first, (_, _, dets, objs) in zip(firsts, batch, strict=True):
            keep(refined(edge_fits, compatible, first, (dets, objs), k0, (width, height)))
    gates = inlier_gate(boxes)
    if fits:
        leading = min(fits, key=lambda f: truncated_cost(f.fit, f.detections, gates))
        for fit in left_out(edge_fits, compatible, leading, k0, (width, height)):
            keep(fit)
    if not fits:
        few = few_detections(compatible, np.argsort(-scores, kind="stable"))
        source: IntrinsicsSource = known_from if given else "scene"
        fits = [
            Fit(f, d, o, source) for f, d, o in few_fits(objects, boxes, masks, compatible, few, k0)
        ]
    ranked = _distinct_best(fits, objects.radius, gates)
    if not ranked:
        nothing = "no camera pose above the ground explains the detections"
        return FreePoseAnswer("failed", nothing, None, (), len(index))
    poses = [_candidate(f, objects, (boxes, masks, labels, index), width) for f in ranked]
    kept = poses
    if attitude is not None:
        kept = _of_attitude(poses, attitude)
        if not kept:
            return _no_pose_of(attitude, poses, len(index))
    answer = _status(kept, objects, (width, lenses, general, unit), len(index))
    if len(kept) == len(poses):
        return answer
    said = f"; the photo's pitch and roll ruled out {len(poses) - len(kept)} other pose(s)"
    return replace(answer, reason=answer.reason + said)


def _off_attitude(pose: PoseCandidate, attitude: tuple[float, float]) -> float:
    """How far (degrees) ``pose``'s down direction lies from the one ``attitude`` states."""
    return attitude_error_deg(rotation_of_quaternion(pose.quaternion_wxyz), *attitude)


def _of_attitude(poses: list[PoseCandidate], attitude: tuple[float, float]) -> list[PoseCandidate]:
    """The ``poses`` within :data:`ATTITUDE_TOLERANCE_DEG` of the photo's ``(pitch, roll)``."""
    return [p for p in poses if _off_attitude(p, attitude) <= ATTITUDE_TOLERANCE_DEG]


def _no_pose_of(
    attitude: tuple[float, float], poses: list[PoseCandidate], usable: int
) -> FreePoseAnswer:
    """``ambiguous`` (``attitude``): none of the ``poses`` keeps to the photo's attitude."""
    nearest = min(_off_attitude(p, attitude) for p in poses)
    reason = (
        "ambiguous: no pose that explains the boxes has the camera's pitch and roll the photo "
        f"states ({attitude[0]:.1f}°, {attitude[1]:.1f}°): the nearest is {nearest:.0f}° off "
        "them; a scene whose ground is not level, a gimbal's angles that are not the camera's, "
        "or boxes of other objects"
    )
    others = tuple(poses[1 : 1 + MAX_ALTERNATIVES])
    return FreePoseAnswer("ambiguous", reason, poses[0], others, usable, "attitude")


def _status(
    poses: list[PoseCandidate],
    objects: SceneObjects,
    context: tuple[float, FocalRange, bool, float],
    usable: int,
) -> FreePoseAnswer:
    """The answer from the ranked distinct ``poses`` (module docstring's status), on a film
    ``context[0]`` wide with the lenses considered, whether the labels are a general model's,
    and the unit of the reasons' pixels; ``usable`` detections."""
    width, lenses, general, unit = context
    best = poses[0]
    ratio = UNIQUE_RATIO_3 if best.inliers == 3 else AMBIGUITY_RATIO
    limit = ratio * max(best.residual_px, NOISE_FLOOR_PX)
    rivals = tuple(p for p in poses[1:] if p.inliers >= best.inliers and p.residual_px <= limit)
    own = "" if not general else f", or {OWN_DETECTOR}"
    if best.inliers < 3:
        reason = (
            f"ambiguous: only {best.inliers} object(s) paired; at least 3 are needed for a "
            f"pose (4 to be sure): a wider view, or a photo with more of the scene's objects{own}"
        )
        others = tuple(poses[1 : 1 + MAX_ALTERNATIVES])
        return FreePoseAnswer("ambiguous", reason, best, others, usable, "few")
    if rivals:
        reason = (
            f"ambiguous: {len(rivals)} distinct pose(s) explain the boxes almost as well "
            f"(edge RMS ≤ {limit * unit:.2f} px against the best {best.residual_px * unit:.2f} "
            f"px): a symmetric layout or look-alike objects; more objects in view{own} would "
            "decide"
        )
        others = rivals[:MAX_ALTERNATIVES]
        return FreePoseAnswer("ambiguous", reason, best, others, usable, "rivals")
    kind, loose = _loose(best, objects.radius, lenses.fov_deg(width))
    if kind is not None:
        others = tuple(poses[1 : 1 + MAX_ALTERNATIVES])
        return FreePoseAnswer("ambiguous", f"ambiguous: {loose}", best, others, usable, kind)
    focal = {
        "estimated": "focal length estimated",
        "scene": "the scene camera's field of view assumed (too few objects to estimate it)",
        "given": "intrinsics given",
        "calibration": "intrinsics from the drone's calibration (the photo's XMP)",
        "exif": "focal length from the photo's EXIF",
    }
    reason = (
        f"found: {best.inliers} objects paired, edge RMS {best.residual_px * unit:.2f} px; "
        f"{focal[best.intrinsics.source]}"
    )
    return FreePoseAnswer("found", reason, best, (), usable)


def _loose(
    best: PoseCandidate, radius: float, lenses: tuple[float, float]
) -> tuple[Ambiguity | None, str]:
    """Why the boxes pin ``best`` too loosely to call it found (module docstring): the kind,
    ``focal`` (the scene camera's fov assumed) or ``loose`` (its σ), and a sentence; or None.
    ``lenses``: the widest and narrowest horizontal fov (degrees) a fit may take."""
    if best.intrinsics.source == "scene" and best.inliers < MIN_FOCAL_PAIRS:
        return "focal", (
            f"only {best.inliers} objects paired and no intrinsics given: the scene camera's "
            "field of view was assumed, and distance trades against focal length; give the "
            "photo's intrinsics, or a view with at least 4 of the scene's objects"
        )
    if best.intrinsics.source == "scene":
        widest, narrowest = lenses
        return "focal", (
            "no intrinsics given, and the boxes would put the field of view beyond the lenses "
            f"considered ({narrowest:.0f}° to {widest:.0f}° across): the scene camera's was "
            "assumed, and distance trades against focal length; give the photo's intrinsics"
        )
    if (
        FIRM_SIGMAS * best.position_sigma > WRONG_POSITION * radius
        or FIRM_SIGMAS * best.rotation_sigma_deg > WRONG_ROTATION_DEG
    ):
        return "loose", (
            f"the boxes pin the pose only loosely (1σ {best.position_sigma:.2g} scene units, "
            f"{best.rotation_sigma_deg:.2g}°): more objects in view, or the photo's intrinsics, "
            "would decide"
        )
    return None, ""


def _failure(
    detections: Sequence[Detection], objects: SceneObjects, confident: NDArray[np.bool_]
) -> str:
    if not detections:
        return "failed: no object was detected in the image; a photo showing the scene's objects"
    if not confident.any():
        return "failed: every detection is below the confidence threshold"
    seen = sorted({d.label for d in detections})
    known = sorted(set(objects.labels) | set(objects.shapes))
    return (
        f"failed: no detection names an object of the scene (labels {', '.join(seen)}; the "
        f"scene's classes are {', '.join(known)}): is the detector the scene's own?"
    )
