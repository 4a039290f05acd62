"""``POST /refine-pose`` as a plain function: a free pose refined densely against the target
image by the render at it (:func:`~services.optimizer.free.refine_dense`), answered in the
contract's terms (:mod:`services.common.contracts.refine`).

Resolution
    The render is made on the target's shape scaled by ``s`` (a search renders at most its
    view width; a small target without its intrinsics up to twice its own size,
    :data:`~services.common.contracts.refine.MAX_FILM_SCALE`). The target is brought to the
    render's film (a large JPEG decoded already shrunk towards it by libjpeg, then
    ``cv2.INTER_AREA``; a smaller one enlarged by ``cv2.INTER_CUBIC``) and the fit
    runs there, on the render's camera: the pose's pixel intrinsics times ``s``; the fitted
    intrinsics are scaled back by ``1 / s`` (the principal point stays the pose's).

Converged
    The fit had at least :data:`~services.optimizer.free.level_fit.MIN_POINTS` model edge points,
    ends with about as many within 2 px of a target edge as the start had (:data:`KEEP_INLIERS`:
not fewer than noise explains), and with at least
    :data:`MIN_INLIER_SHARE` of them there: a pose that explains the image leaves most of its
    edges on the target's, a fit lost in clutter does not.

Accepted
    Converged, and moved plausibly. A near move (:data:`MAX_MOVE` of the
    points' median depth ``z̃``, plus ``|k - 1| z̃`` when the focal length changed by ``k``: a
    dolly zoom trades the two; :data:`MAX_TURN_DEG`) is what the box fit errs by on most
    targets (issue 23's box-only simulation: 97 % within 10 % and 5°). Through the real
    detector the box pose is sometimes further off (measured on the built-in and generated
    scenes: up to 0.4 r and 14°), and the fit brought 4 of 6 such poses to within 0.01 r and
    0.3° and the other 2 closer, each explaining 1.3-3.3 times the start's edge points; a
    move beyond the near bounds is accepted only when the image vouches for it, the fit explaining
    at least :data:`FAR_GAIN` times the start's edge points, and up to :data:`FAR` times the
    near bounds. Anything further is taken for a slip of the fit into another basin (a repeated
    texture), and the box pose is kept.

    Whether it slipped or found the pose, a render where it ended tells, not the fit: a fit
    that moved too far but leaves at least :data:`FAR_SHARE` of its edge points on the target's,
    :data:`LEAD_GAIN` times the start's, within :data:`LEAD_REACH` times the points' median
    depth, is a ``lead`` (not accepted; the controller renders it and checks that render as it
    checks any). Measured through the real stack (``cosmos bench --free --scene demo,garden
    --random-scenes 2 --n 8``, seeds 1-4, 640 searches, one run each way): within 5 % / 2°
    476 → 483, none confirmed wrong either way, 1207 → 1209 renders in all. A garden view of
    three objects whose box pose was 41 % / 38° off (its fit: 289 → 1694 of 2000 edge points)
    was found within 0.4 % / 0.3° in its clean, JPEG and photo variants.

    The fit must also keep to the boxes it started from, unless the image vouches for leaving
    them: when it moves the paired objects' predicted box edges by more than the box fit can
    err (RMS shift over ``max(BOX_SLACK_PX / min(s, 1), BOX_SLACK_RATIO · r)`` target pixels,
    ``r`` the start's box-edge RMS, ``s`` the render's film over the target's: a film larger
    than the target makes the detector's boxes no finer), it is accepted only when
    it leaves at least :data:`FAR_SHARE` of its edge points on the target's. Measured through
    the real stack (``cosmos bench --free --scene demo --random-scenes 2 --n 8 --seed 5``, the
    targets and renders 320 pixels wide): fits that moved the boxes 2-6 px and left 0.52-0.72
    of their edges were all wrong, two of them confirmed (a moved light let shadow edges pull a
    right box pose 10-18 % / 6-9° away); right fits that moved the boxes that far (2-25 px: the
    general model's boxes were wrong) left 0.796-0.97.

Focal check
    A pose whose focal length was stated, not given (the photo's EXIF: ``check_focal``), is
    fitted with it, and fitted again from the same render with the focal length free, bounded
    about the stated one (``focal_check``): whether the image bears the statement out is the
    controller's to judge (:mod:`services.controller.exif_check`).

Lens check
    Unless the pose states a lens, the fit's lens check says whether the target's edges bend as
    a distorting lens's, and gives the pose fitted through that lens
    (:mod:`services.optimizer.lens_pose`). A pose whose lens an earlier check estimated
    (``fit_lens``: rendered through it) is fitted through it and checked again from there.

Above chance
    Every share here, and the counts compared with the start's, are taken above the share a
    pose placed at random would leave on the target's edges (``chance``,
    :func:`~services.common.contracts.free.above_chance`): on an edge-rich target (gravel,
    foliage, sensor noise) any pose's points find edges. The figures above were measured on
    rendered targets, where that chance is 1-3 %. Under a strong noise texture (chance 0.54) a
    fit from a render of another view moved 651 units and left 0.82 of its points on the
    target's edges, enough to converge; above chance it left 0.60.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from services.common.catalog import SceneCatalog
from services.common.contracts.free import DenseReport, FreePose
from services.common.contracts.refine import (
    MAX_FILM_SCALE,
    FocalCheck,
    RefinePoseRequest,
    RefinePoseResponse,
    TargetRequest,
    TargetResponse,
)
from services.common.depth_archive import DepthImage
from services.common.errors import ServiceError, UnprocessableError
from services.common.geometry.camera import focal_length_px
from services.common.geometry.free_camera import (
    free_pinhole_camera,
    rotation_angle_deg,
)
from services.common.images import checked_header, decode_image
from services.optimizer.free import DenseFit, refine_dense
from services.optimizer.free.dense import ZOOM_STARTS, pyramid, radial_only
from services.optimizer.free.edges import on_film, outline
from services.optimizer.free.focal_bounds import FocalRange
from services.optimizer.free.level_fit import MIN_POINTS
from services.optimizer.free.refit import worth_another_render
from services.optimizer.free.target_maps import TargetMapCache
from services.optimizer.free_pose import SceneObjectCache, predicted_boxes
from services.optimizer.lens_pose import lens_bend, lens_pose

__all__ = [
    "CHECK_ZOOMS",
    "FAR",
    "FAR_GAIN",
    "FAR_SHARE",
    "LEAD_GAIN",
    "LEAD_REACH",
    "MAX_MOVE",
    "MAX_TURN_DEG",
    "MIN_INLIER_SHARE",
    "ImageLimits",
    "converges",
    "dense_report",
    "prepare_target",
    "refine_pose",
]

MIN_INLIER_SHARE: Final = 0.5
"""The share of the model edge points a converged fit leaves within 2 px of a target edge."""
KEEP_INLIERS: Final = 0.98
"""A converged fit keeps at least this share of the start's explained points: a start already
on the target moves by noise, and its count by a few points either way."""
MAX_MOVE: Final = 0.1
"""A near move of the camera, as a share of the points' median depth."""
MAX_TURN_DEG: Final = 5.0
"""A near turn of the camera, in degrees."""
FAR: Final = 4.0
"""A move up to this many times the near bounds is plausible when the image vouches for it."""
FAR_GAIN: Final = 1.2
"""…that is, when the fit explains this many times the start's edge points."""
BOX_SLACK_PX: Final = 2.0
"""Box-edge shift any fit may make, in pixels of the render's film (at most the view width, as
the detector sees a target: a photo's own pixels are that many times finer): about three times
the detector's measured box-edge error."""
BOX_SLACK_RATIO: Final = 3.0
"""…or this many times the start's own box-edge RMS, when its boxes fitted worse."""
FAR_SHARE: Final = 0.75
"""The share of its edge points on the target's that a fit leaving the boxes needs (and a
``lead``)."""
LEAD_GAIN: Final = 2.0
"""A fit that moved too far is a ``lead`` when it explains this many times the start's points…"""
LEAD_REACH: Final = 1.0
"""…and moved at most this many times the points' median depth."""
_SIDE_SLACK_PX: Final = 1.0
CHECK_ZOOMS: Final = (1.0,)
"""The focal check (``check_focal``) starts from the stated focal length alone, not from every
zoom of :data:`~services.optimizer.free.dense.ZOOM_STARTS` as a fit without intrinsics does.
``python -m benchmarks.exif_check`` (576 fits each, one run on a loaded machine): 1.6 times the
fit of the pose alone (median 139 against 85 ms), from every zoom 5.0 times (423 ms); from
every zoom it overruled a few more wrong EXIFs (35, 47 and 44 of 96 within 5 %/2° with the EXIF
15 % long, 5 % long and 5 % short, against 31, 40 and 42), and the right ones alike."""
CHANCE_SAID: Final = 0.05
"""A target edge density at which the reasons say what share a random pose would explain."""


@dataclass(frozen=True)
class ImageLimits:
    """The largest target image decoded: pixels and side."""

    max_pixels: int
    max_side: int


def _invalid(detail: str, field: str) -> UnprocessableError:
    return UnprocessableError(detail, field=field, slug="invalid-request")


def _target_size(data: bytes, limits: ImageLimits) -> tuple[int, int]:
    """The target image's (width, height), as its header declares them (checked)."""
    try:
        header = checked_header(data, max_pixels=limits.max_pixels, max_side=limits.max_side)
    except ServiceError as exc:
        exc.field = "target"
        raise
    return header.width, header.height


def _target_gray(data: bytes, limits: ImageLimits, film: tuple[int, int]) -> NDArray[np.uint8]:
    """The target in grey on the render's ``film`` ``(w, h)``: a large JPEG decoded already
    shrunk to no less than twice the film (:func:`~services.common.images.decode_image`), then
    brought to it by ``cv2.INTER_AREA``. Shrunk to the film itself (libjpeg keeping only each
    8 x 8 block's mean), a 4000 x 3000 photo's fit left 601 of 631 edge points on its edges
    against 622 from the whole decode; at twice the film, as many as whole, the grey 0.25
    levels from it on average, in 22-26 ms against 81-98 ms. A target smaller than the film is
    enlarged by ``cv2.INTER_CUBIC``: its edges, found on the enlarged grey, fall between its
    own pixels."""
    twice = (2 * film[0], 2 * film[1])
    try:
        rgb = decode_image(
            data, max_pixels=limits.max_pixels, max_side=limits.max_side, at_least=twice
        )
    except ServiceError as exc:
        exc.field = "target"
        raise
    gray = np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
    return on_film(gray, film)


def _render(data: bytes, target: tuple[int, int]) -> tuple[DepthImage, NDArray[np.uint8], float]:
    """The render's archive, its colours and its scale ``s`` from the target (checked)."""
    try:
        render = DepthImage.from_npz(data)
    except ValueError as exc:
        raise _invalid(str(exc), "render") from exc
    if render.rgb is None:
        raise _invalid("the render's archive has no rgb (ask the renderer for it)", "render")
    h, w = render.depth.shape
    return render, render.rgb, _film_scale((w, h), target, "the render", "render")


def _film_scale(film: tuple[int, int], target: tuple[int, int], what: str, field: str) -> float:
    """``s``, the ``film``'s width over the ``target``'s, when the film has the target's shape
    and is at most :data:`~services.common.contracts.refine.MAX_FILM_SCALE` times its size (else
    a 422 naming ``field``)."""
    (w, h), (width, height) = film, target
    scale = w / width
    if not (8 <= w <= MAX_FILM_SCALE * width and abs(h - height * scale) <= _SIDE_SLACK_PX):
        raise _invalid(
            f"{what} is {w}x{h}: not the target's {width}x{height} shape at most "
            f"{MAX_FILM_SCALE:g} times its size",
            field,
        )
    return scale


def box_shift_px(
    start: FreePose, boxes: Mapping[str, tuple[float, float, float, float] | None]
) -> float:
    """The RMS shift (target pixels) of the paired objects' predicted box edges from the start
    pose's to ``boxes`` (by object name); 0 when none projects at both."""
    shifts = [
        np.subtract(box, c.predicted_box)
        for c in start.correspondences
        if c.predicted_box is not None and (box := boxes.get(c.object)) is not None
    ]
    return float(np.sqrt(np.mean(np.square(shifts)))) if shifts else 0.0


def _chance_said(fit: DenseFit) -> str:
    """``; a random pose would leave N %``, on an edge-rich target (:data:`CHANCE_SAID`)."""
    return f"; a random pose would leave {fit.chance:.0%}" if fit.chance >= CHANCE_SAID else ""


def converges(fit: DenseFit) -> bool:
    """Whether ``fit`` converged (module docstring): enough points, at least about as many
    explained as at the start, and :data:`MIN_INLIER_SHARE` of them, every share above the
    target's chance (a raw count would let a fit lost in texture converge on the edges it lands
    on anywhere)."""
    end, begin = fit.share(), max(fit.share(fit.start_inliers), 0.0)
    return fit.points >= MIN_POINTS and end >= KEEP_INLIERS * begin and end >= MIN_INLIER_SHARE


def dense_report(
    fit: DenseFit,
    start: FreePose,
    depth: float,
    scale: float,
    *,
    box_shift: float = 0.0,
    render_again: bool = False,
) -> DenseReport:
    """How the ``fit`` from ``start`` (rendered at ``scale`` times the target's film, its
    points at median depth ``depth``) went: converged, accepted and why (module docstring);
    ``box_shift`` is :func:`box_shift_px` at the fit; ``render_again``
    (:func:`~services.optimizer.free.refit.worth_another_render`) is kept for an accepted fit
    only."""
    moved = float(np.linalg.norm(fit.position - np.asarray(start.position)))
    turned = rotation_angle_deg(fit.rotation.T, start.camera().rotation())
    zoom = fit.intrinsics.fx / (start.intrinsics.fx_px * scale)
    end, begin = fit.share(), max(fit.share(fit.start_inliers), 0.0)
    converged = converges(fit)
    allowed = (MAX_MOVE + abs(zoom - 1.0)) * depth
    near = moved <= allowed and turned <= MAX_TURN_DEG
    vouched = end >= FAR_GAIN * begin
    plausible = near or (vouched and moved <= FAR * allowed and turned <= FAR * MAX_TURN_DEG)
    slack = max(BOX_SLACK_PX / min(scale, 1.0), BOX_SLACK_RATIO * start.residual_px)
    kept_boxes = box_shift <= slack or end >= FAR_SHARE
    accepted = converged and plausible and kept_boxes
    lead = (
        converged
        and not plausible
        and end >= FAR_SHARE
        and end >= LEAD_GAIN * begin
        and moved <= LEAD_REACH * depth
    )
    if not converged:
        reason = (
            f"the dense fit did not converge: {fit.inliers} of {fit.points} edge points end on "
            f"the target's edges ({fit.start_inliers} at the start{_chance_said(fit)})"
        )
    elif not plausible:
        reason = (
            f"the dense fit moved the pose implausibly far ({moved:.3g} units, {turned:.2g}°, "
            f"explaining {fit.inliers} edge points where the start explained "
            f"{fit.start_inliers}; at most {allowed:.3g} units and {MAX_TURN_DEG:g}°, or "
            f"{FAR:g} times that with {FAR_GAIN:g} times the edge points)"
        )
        if lead:
            reason += "; worth a render where it ended"
    elif not kept_boxes:
        reason = (
            f"the dense fit moved the boxes {box_shift:.3g} px from the box pose's (at most "
            f"{slack:.3g} px) with only {fit.inliers} of {fit.points} edge points on the "
            f"target's (at least {FAR_SHARE:.0%} would vouch for it)"
        )
    else:
        reason = (
            f"refined by the render's edges: {fit.inliers} of {fit.points} edge points on the "
            f"target's ({fit.start_inliers} before; boxes moved {box_shift:.2g} px"
            f"{_chance_said(fit)})"
        )
    residual = fit.residual_px / scale if math.isfinite(fit.residual_px) else None
    return DenseReport(
        converged=converged,
        accepted=accepted,
        reason=reason,
        edge_points=fit.points,
        inliers=fit.inliers,
        start_inliers=fit.start_inliers,
        residual_px=residual,
        focal_fitted=fit.focal_fitted,
        moved=moved,
        moved_rotation_deg=turned,
        render_again=render_again and accepted,
        box_shift_px=box_shift,
        focal_sigma=fit.focal_sigma if math.isfinite(fit.focal_sigma) else None,
        chance=fit.chance,
        lead=lead,
        lens=lens_bend(fit.radial, scale, accepted),
    )


def _refined(
    fit: DenseFit, start: FreePose, report: DenseReport, scale: float, width: int
) -> FreePose:
    """``start`` moved to the fit (intrinsics in target pixels, module docstring)."""
    k = start.intrinsics
    fx, fy = fit.intrinsics.fx / scale, fit.intrinsics.fy / scale
    source = "estimated" if fit.focal_fitted else k.source
    intrinsics = k.refocused(fx, fy, width, source, k.distortion)
    residual = report.residual_px if report.residual_px is not None else 0.0
    return start.moved_to(fit.rotation.T, fit.position, intrinsics, residual)


def refine_pose(
    request: RefinePoseRequest,
    target: bytes,
    render: bytes,
    catalog: SceneCatalog | None,
    cache: SceneObjectCache,
    limits: ImageLimits,
    targets: TargetMapCache | None = None,
) -> RefinePoseResponse:
    """The request's pose refined against ``target`` (the image's bytes) by ``render`` (the
    archive of the render at the pose) (module docstring); ``targets`` keeps the target's maps
    for the search's next render (:mod:`~services.optimizer.free.target_maps`)."""
    if catalog is None:
        raise _invalid("this optimizer has no scene catalog", "request.scene")
    scene = catalog.get(request.scene)  # NotFoundError (404) names the field
    lens = request.pose.intrinsics.distortion
    if request.fit_lens and (lens is None or not radial_only(lens)):  # before any decoding
        detail = "fit_lens asks for a pose whose lens distortion is a radial k1 alone"
        raise _invalid(detail, "request.fit_lens")
    width, height = _target_size(target, limits)
    view, rgb, scale = _render(render, (width, height))
    h, w = view.depth.shape
    targets = targets or TargetMapCache(0)
    maps = targets.maps(target, (w, h), lambda: _target_gray(target, limits, (w, h)))
    start = request.pose
    k = start.intrinsics
    names = [c.object for c in start.correspondences]
    objects = cache.get(scene)
    if any(n not in objects.names for n in names):  # before the fit: a bad request costs none
        raise _invalid("the pose pairs an object the scene does not have", "request.pose")
    try:
        at = start.camera()
    except ValidationError as exc:
        raise _invalid(
            f"the pose is not a camera: {exc.errors()[0]['msg']}", "request.pose"
        ) from exc
    camera = at.model_copy(
        update={
            "fx_px": k.fx_px * scale,
            "fy_px": k.fy_px * scale,
            "cx_px": k.cx_px * scale,
            "cy_px": k.cy_px * scale,
            "distortion": None,
        }
    )
    pinhole = free_pinhole_camera(camera, w, h, k.fov_deg)
    near = None if view.shading is None else outline(view.depth, view.objects, view.shading)
    hits = view.depth[view.depth > 0.0]
    depth = float(np.median(hits)) if hits.size else math.inf

    def fitted(
        fit_focal: bool,
        lenses: FocalRange,
        zooms: tuple[float, ...] = ZOOM_STARTS,
        lens_check: bool = True,
    ) -> RefinePoseResponse:
        """The fit from the render (the focal length free or not, within ``lenses`` on the
        film, started from ``zooms`` of the pose's; with the lens check when no lens is known
        and ``lens_check``) as the contract answers it."""
        fit = refine_dense(
            maps,
            rgb,
            view.depth,
            pinhole,
            fit_focal=fit_focal,
            distortion=k.distortion,
            near=near,
            pixel=max(scale, 1.0),
            focal_range=lenses,
            zooms=zooms,
            check_radial=lens_check and (k.distortion is None or request.fit_lens),
            radial_focal=fit_focal or request.check_focal,
        )
        again = worth_another_render(fit, pinhole)
        focal = (fit.intrinsics.fx / scale, fit.intrinsics.fy / scale, k.cx_px, k.cy_px)
        position = (float(fit.position[0]), float(fit.position[1]), float(fit.position[2]))
        boxes = predicted_boxes(objects, names, fit.rotation.T, position, focal, k.distortion)
        shift = box_shift_px(start, boxes)
        report = dense_report(fit, start, depth, scale, box_shift=shift, render_again=again)
        pose = _refined(fit, start, report, scale, width)
        pairs = tuple(
            c.model_copy(update={"predicted_box": boxes[c.object]}) for c in start.correspondences
        )
        bent = None
        if report.lens is not None and report.lens.bends and fit.radial is not None:
            bent = lens_pose(fit.radial, start, report, (width, height), objects)
        return RefinePoseResponse(
            pose=pose.model_copy(update={"correspondences": pairs}), fit=report, lens_pose=bent
        )

    scene_focal = focal_length_px(scene.spec.camera.fov_deg, w)
    answer = fitted(request.fit_focal, FocalRange.of(scene_focal, w, h))
    if not request.check_focal or request.fit_focal:
        return answer
    check = fitted(True, FocalRange.about(pinhole.fx), CHECK_ZOOMS, lens_check=False)
    return answer.model_copy(update={"focal_check": FocalCheck(pose=check.pose, fit=check.fit)})


def prepare_target(
    request: TargetRequest, target: bytes, limits: ImageLimits, targets: TargetMapCache
) -> TargetResponse:
    """The ``target`` image's grey image on the request's film and its distance maps (every
    level when the focal length will be fitted, else the finest), made and kept in ``targets``
    for the refinements of the search to come (``POST /refine-pose/target``)."""
    film = request.film
    scale = _film_scale(film, _target_size(target, limits), "the film", "request.film")
    maps = targets.maps(target, film, lambda: _target_gray(target, limits, film))
    levels = pyramid(max(scale, 1.0))
    levels = levels if request.fit_focal else levels[-1:]
    for level in levels:
        maps.level(*level)
    kept = all(maps.kept(*level) for level in levels)
    return TargetResponse(film=film, levels=len(levels), kept=kept)
