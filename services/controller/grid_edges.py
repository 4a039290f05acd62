"""A hemisphere search's answer settled by the render's edges: an unconfirmed one, or one
confirmed near a boundary between grid poses.

The reprojection strategy's answer is the grid pose nearest its estimate from the boxes. With
few objects, or a target between grid poses, that estimate can sit a few degrees off and pick a
neighbour of the true grid pose; the search then says it is not sure (``confirmed`` false). One
render of the answer's pose, with its depth, settles it: the optimizer's dense fit (``POST
/refine-pose``, the free search's, the scene camera's intrinsics kept) moves that render's
edges onto the target's, and the camera it ends at gives the direction

.. math:: θ = \\arccos(z / ‖c‖), \\quad φ = \\operatorname{atan2}(y, x)

from the scene centre, whose nearest grid pose becomes the answer. It does so only when the fit
was accepted, leaves at least :data:`SETTLE_SHARE` of its edge points (and
:data:`~.free_refine.MIN_PIN_POINTS` of them) on the target's, and its camera stands on the
hemisphere, within :data:`ON_SPHERE` of the radius, as a hemisphere target's does.

Measured with ``python -m benchmarks.grid_edges`` (seeds 41 and 42: the demo and two generated
scenes each, 8 off-grid targets per scene, clean and with pixel noise, 464 fits): from a render
at the true grid pose, 94 of 96 fits settled the answer, all at the true grid pose; from a
render at one of its neighbours (an answer the boxes got wrong), 274 of 368 settled it, 272 at
the true grid pose (0 → 272 answers right), the direction within 0.16° median. An answer the
edges move is unconfirmed: the render was not made at the pose they moved it to.

A confirmed answer is checked so when its estimate lies near a boundary
(:func:`near_a_boundary`): the strategy confirms between neighbours by comparing their views,
which is not the same as the nearest grid pose. It stays confirmed when the edges keep it. So
too, when its estimate looks steeply down (:func:`steep`): there the views of neighbouring
rings hardly differ, and such an answer stays confirmed only when the edges keep it; when they
cannot tell (the fit refused, or no render), it is no longer confirmed.

Only the reprojection strategy's answers are settled so: ``simple`` and ``paper`` are the
paper's strategies, measured as it describes them. The render counts in the answer's renders.
"""

from __future__ import annotations

import logging
import time
from typing import Final

import numpy as np

from services.common.contracts.free import FreePose, IntrinsicsUsed
from services.common.contracts.optimize import GridPose, SearchableGrid
from services.common.contracts.refine import RefinePoseRequest, RefinePoseResponse
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import Search, SearchResult, StageTimings
from services.common.geometry.camera import pinhole_camera
from services.common.geometry.free_camera import (
    direction_pose,
    quaternion_of_rotation,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.pose import Pose
from services.common.geometry.sphere import angular_distance_deg
from services.controller.failures import SearchFailed
from services.controller.free_match import scaled_camera, view_film
from services.controller.free_refine import MIN_PIN_POINTS, ask_refinement, fit_pins
from services.controller.outages import OutagePolicy
from services.controller.stages import Stages

__all__ = [
    "BOUNDARY_SHARE",
    "EDGE_STRATEGY",
    "ON_SPHERE",
    "SETTLE_SHARE",
    "STEEP_THETA_DEG",
    "grid_free_pose",
    "near_a_boundary",
    "settle_by_edges",
    "settled_result",
    "steep",
]

_log = logging.getLogger("cosmos.controller")

EDGE_STRATEGY: Final = "reprojection"
"""The strategy whose answers the render's edges settle."""
SETTLE_SHARE: Final = 0.7
"""The share of the render's edge points an accepted fit must leave on the target's (above
chance) to settle the answer. In the benchmark's run (module docstring) no bound moved a right
answer; from a neighbour, 0.5 settled 297 answers (295 right), 0.7 274 (272), 0.9 117 (117). The
bound is kept above the least a fit converges with (0.5) for the targets it did not measure (a
changed light, a moved object), where a fit may hold on to part of the image."""
BOUNDARY_SHARE: Final = 0.25
"""A confirmed answer whose estimate lies this share of a step from nearer another grid pose
(:func:`near_a_boundary`) is checked by the render's edges too: the strategy may have confirmed
it by comparing views, and near the zenith a view's boxes follow φ more than θ, so the grid pose
whose view matches best need not be the nearest. In the runs of 2026-12-06 (2,720 reprojection
searches: ``cosmos bench --profile --n 20`` and ``cosmos bench --random-scenes 5 --n 5``, seeds
7-10) 29 confirmed answers lay within 2° so (of a 7.5° or 5° step), one of them wrong: a garden
target at θ 17.2° confirmed at θ 22.5° (its estimate 0.95° inside), the view of the true grid
pose, 9° away in φ, matching worse."""
STEEP_THETA_DEG: Final = 30.0
"""A confirmed answer whose estimate lies below this θ (the camera looking more than 60° down)
is checked by the render's edges, and keeps its confirmation only when they keep it
(:func:`steep`). Near the zenith the boxes tell θ least: in the hemisphere runs of 2026-12-06
(``cosmos bench --random-scenes 5 --n 5``, seeds 7-11, 3,000 reprojection searches), the
refined direction's error at θ < 30° had p90 1.4-1.9° and p99 6.5-8.9°, at 30-60° 0.8-0.9° and
3.6-5.0°; every answer confirmed wrong lay below 30°: the garden's at θ 17.2° (caught near a
boundary), and on seed 11, with the scene's own model, a JPEG target at θ 15° whose true view
the views rejected (one object not detected) and which was confirmed at θ 20° (given and
predicted start alike), and a noisy one at θ 7° confirmed at θ 14°, its estimate 12.1°. The
same 300 searches with the scenes' own models, one run before and one after this check:
confirmed wrong 3 → 0, found 296 → 299, confirmed right 280 → 272 (right answers below 30° whose
fit could not settle them, six under another light), renders 616 → 652, the median with a
predicted start still 1 (docs/EVALUATION.md)."""
ON_SPHERE: Final = 0.01
"""How far (a share of the radius) a settling fit's camera may stand off the hemisphere. In the
benchmark's run, from a neighbour at a share of 0.7: within 0.5 %, 268 settled (266 right);
1 %, 274 (272); 2 and 5 %, 276 (272)."""


def grid_free_pose(pose: Pose, radius: float, fov_deg: float, size: tuple[int, int]) -> FreePose:
    """The hemisphere camera at ``pose`` as a free pose on a target of ``size`` (width, height)
    pixels: the scene camera's field of view across its width, no pairs."""
    width, height = size
    camera = pinhole_camera(pose, radius, fov_deg, width, height)
    camera_to_world = np.asarray(camera.rotation, dtype=np.float64).T
    return FreePose(
        position=camera.position,
        quaternion_wxyz=quaternion_of_rotation(camera_to_world),
        yaw_pitch_roll_deg=yaw_pitch_roll_of_rotation(camera_to_world),
        intrinsics=IntrinsicsUsed(
            fx_px=camera.fx,
            fy_px=camera.fy,
            cx_px=camera.cx,
            cy_px=camera.cy,
            fov_deg=fov_deg,
            source="scene",
        ),
        correspondences=(),
        residual_px=0.0,
        confidence=0.0,
        position_sigma=None,
        rotation_sigma_deg=None,
    )


def settled_result(
    result: SearchResult,
    outcome: RefinePoseResponse | str,
    grid: SearchableGrid,
    radius: float,
    *,
    share: float = SETTLE_SHARE,
    on_sphere: float = ON_SPHERE,
    min_points: int = MIN_PIN_POINTS,
    vouch: bool = False,
) -> SearchResult:
    """``result`` (one render more) with the dense fit's ``outcome`` from the render at its
    pose (module docstring): its grid pose and direction when the fit pins a camera on the
    hemisphere (``share``, ``on_sphere`` and ``min_points`` the bounds), else as it was; the
    reason says which. A confirmed answer stays confirmed unless the fit moves it to another
    grid pose, or, with ``vouch`` (a steep view: :func:`steep`), unless the fit cannot pin it."""
    renders = result.renders + 1
    if isinstance(outcome, str):
        return _unsettled(result, outcome, renders, vouch)
    fit = outcome.fit
    off = float(np.linalg.norm(outcome.pose.position)) / radius - 1.0
    why = ""
    if not fit.accepted:
        why = fit.reason
    elif not fit_pins(fit, min_points, share):
        why = f"{fit.inliers} of {fit.edge_points} edge points on the target's: too few to pin it"
    elif abs(off) > on_sphere:
        why = f"its camera stands {off:+.1%} of the radius off the hemisphere"
    if why:
        return _unsettled(result, why, renders, vouch)
    direction = direction_pose(outcome.pose.position)
    index = grid.grid().nearest(direction)
    on_grid = grid.grid().pose(index)
    nearest = GridPose(index=index, theta_deg=on_grid.theta_deg, phi_deg=on_grid.phi_deg)
    where = (
        f"the render's edges put the camera at θ = {direction.theta_deg:.2f}°, φ = "
        f"{direction.phi_deg:.2f}° ({fit.inliers} of {fit.edge_points} edge points on the "
        "target's)"
    )
    if nearest.index == result.pose.index:
        reason = f"{result.reason}; {where}: nearest this grid pose"
        confirmed = result.confirmed
    else:
        was = result.pose.index
        moved = (
            f"{where}: nearest lat {index.lat} lon {index.lon}, not lat {was.lat} lon {was.lon} "
            "(not rendered there)"
        )
        reason = f"{result.reason}; {moved}"
        if result.confirmed:
            reason = f"not confirmed: {moved}; the views had confirmed it: {result.reason}"
        confirmed = False
    return result.model_copy(
        update={
            "pose": nearest,
            "refined_pose": direction,
            "renders": renders,
            "reason": reason,
            "confirmed": confirmed,
        }
    )


def near_a_boundary(result: SearchResult, grid: SearchableGrid) -> bool:
    """Whether ``result``'s ``refined_pose`` lies within :data:`BOUNDARY_SHARE` of a step
    nearer another grid pose than its own: ``min_{g ≠ a} ∠(r, g) − ∠(r, a) < b Δ`` (``r`` the
    refined direction, ``a`` the answer's grid pose, ``Δ`` the step)."""
    hemisphere = grid.grid()
    angles = angular_distance_deg(result.refined_pose, (hemisphere.theta_deg, hemisphere.phi_deg))
    own = hemisphere.flat(result.pose.index)
    margin = float(np.min(np.delete(angles, own)) - angles[own])
    return margin < BOUNDARY_SHARE * grid.angle_step_deg


def steep(result: SearchResult) -> bool:
    """Whether ``result``'s estimate (its ``refined_pose``), or its grid pose, lies below
    :data:`STEEP_THETA_DEG`."""
    return min(result.refined_pose.theta_deg, result.pose.theta_deg) < STEEP_THETA_DEG


async def settle_by_edges(
    stages: Stages,
    outages: OutagePolicy,
    search: Search,
    scene: SceneDetail,
    grid: SearchableGrid,
    image: bytes,
    size: tuple[int, int],
    result: SearchResult,
    *,
    vouch: bool = False,
) -> SearchResult:
    """``result``, an answer of ``search`` for the target ``image`` of ``size``, settled by a
    render with depth at its pose (module docstring); as it was when that render fails (the
    search keeps the answer it has, and the reason says why), unconfirmed with ``vouch`` (a
    confirmation the edges must bear out: :func:`settled_result`)."""
    sid = search.id
    camera = scene.spec.camera
    at = Pose(theta_deg=result.pose.theta_deg, phi_deg=result.pose.phi_deg)
    pose = grid_free_pose(at, camera.radius, camera.fov_deg, size)
    settings = stages.settings_for(search.view_settings)
    film, scale = view_film(size, settings.width or camera.width)
    started = time.perf_counter()
    try:
        archive = await outages.call(
            sid,
            lambda: stages.render_camera(
                search.scene, scaled_camera(pose, scale), film, sid, settings, with_depth=True
            ),
        )
    except SearchFailed as exc:
        _log.warning("search %s: no render for the edges: %s", sid, exc)
        why = exc.problem.detail or exc.problem.title
        return _unsettled(result, f"no render: {why}", result.renders, vouch)
    render_ms = (time.perf_counter() - started) * 1000
    request = RefinePoseRequest(scene=search.scene, pose=pose)
    outcome = await ask_refinement(stages, outages, sid, request, image, archive)
    total_ms = (time.perf_counter() - started) * 1000
    timings = StageTimings(render_ms=render_ms, refine_ms=total_ms - render_ms, total_ms=total_ms)
    settled = settled_result(result, outcome, grid, camera.radius, vouch=vouch)
    return settled.model_copy(update={"refit_timings": timings})


def _unsettled(result: SearchResult, why: str, renders: int, vouch: bool) -> SearchResult:
    """``result`` with ``renders``, when the render's edges did not settle it (``why``): as it
    was, or no longer confirmed with ``vouch``."""
    if vouch and result.confirmed:
        reason = (
            f"not confirmed: looking {90.0 - result.refined_pose.theta_deg:.0f}° down, the views "
            f"hardly tell the rings apart, and the render's edges did not settle it ({why}); "
            f"the views had confirmed it: {result.reason}"
        )
        return result.model_copy(update={"renders": renders, "reason": reason, "confirmed": False})
    reason = f"{result.reason}; the render's edges did not settle it ({why})"
    return result.model_copy(update={"renders": renders, "reason": reason})
