"""When a dense fit is taken (:func:`services.optimizer.refine_pose.dense_report`): converged
fits that move the pose a little, or further when the image vouches for it; never a fit lost in
clutter, nor one that slipped far."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from services.common.contracts.free import FreeCorrespondence, FreePose, IntrinsicsUsed
from services.common.geometry.free_camera import (
    FreeCamera,
    free_pinhole_camera,
    quaternion_of_rotation,
)
from services.optimizer.free import DenseFit, Intrinsics
from services.optimizer.free.lens_check import RadialCheck
from services.optimizer.free.refit import worth_another_render
from services.optimizer.refine_pose import box_shift_px, dense_report

START = FreeCamera(position=(0.0, -10.0, 5.0), look_at=(0.0, 0.0, 0.0))
DEPTH = 10.0  # the points' median depth: near bounds 1 unit and 5°


def start_pose() -> FreePose:
    return FreePose(
        position=START.position,
        quaternion_wxyz=quaternion_of_rotation(START.rotation()),
        yaw_pitch_roll_deg=(0.0, 0.0, 0.0),
        intrinsics=IntrinsicsUsed(
            fx_px=400.0, fy_px=400.0, cx_px=160.0, cy_px=120.0, fov_deg=43.6, source="given"
        ),
        correspondences=(),
        residual_px=0.5,
        confidence=0.9,
        position_sigma=None,
        rotation_sigma_deg=None,
    )


def fit(
    shift: float, turn_deg: float, inliers: int, start_inliers: int, points=1000, chance=0.0
) -> DenseFit:
    """A fit of the start camera moved ``shift`` along x and turned ``turn_deg`` about z."""
    start = START.rotation().T  # world to camera
    a = math.radians(turn_deg)
    about_z = np.array(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]]
    )
    rotation = start @ about_z.T
    position = np.asarray(START.position) + [shift, 0.0, 0.0]
    return DenseFit(
        rotation=rotation,
        translation=-rotation @ position,
        intrinsics=Intrinsics(400.0, 400.0, 160.0, 120.0),
        residual_px=0.5,
        points=points,
        inliers=inliers,
        start_inliers=start_inliers,
        chance=chance,
    )


@pytest.mark.parametrize(
    ("shift", "turn", "inliers", "start", "accepted", "said"),
    [
        (0.5, 2.0, 900, 880, True, "refined by the render's edges"),
        (0.5, 2.0, 870, 880, True, "refined"),  # about as many as at the start: noise
        (3.0, 9.0, 900, 400, True, "refined"),  # far, and the image vouches for it
        (3.0, 9.0, 900, 800, False, "implausibly far"),  # far, barely better explained
        (5.0, 9.0, 900, 400, False, "implausibly far"),  # beyond 4 times the near bounds
        (0.5, 25.0, 900, 400, False, "implausibly far"),
        (0.5, 2.0, 400, 300, False, "did not converge"),  # most edges unexplained
        (0.5, 2.0, 800, 880, False, "did not converge"),  # worse than the start
    ],
)
def test_a_fit_is_taken_when_it_converged_and_moved_plausibly(
    shift, turn, inliers, start, accepted, said
):
    report = dense_report(fit(shift, turn, inliers, start), start_pose(), DEPTH, 1.0)
    assert report.accepted is accepted, report.reason
    assert said in report.reason
    assert report.moved == pytest.approx(shift)
    assert report.moved_rotation_deg == pytest.approx(turn)


@pytest.mark.parametrize(
    ("shift", "turn", "inliers", "start", "lead"),
    [
        (3.3, 38.0, 850, 150, True),  # far, most edges on the target's, many times the start's
        (9.5, 20.0, 850, 150, True),  # as far as the points' depth
        (12.0, 20.0, 850, 150, False),  # further than the points' depth: a slip
        (3.3, 38.0, 700, 150, False),  # 70 %: the image only partly behind it
        (3.3, 38.0, 850, 500, False),  # less than twice the start's
        (0.5, 2.0, 900, 150, False),  # a near move is accepted, not a lead
        (0.5, 2.0, 400, 100, False),  # did not converge
    ],
)
def test_a_fit_too_far_to_take_is_a_lead_when_the_image_vouches_for_where_it_ended(
    shift, turn, inliers, start, lead
):
    report = dense_report(fit(shift, turn, inliers, start), start_pose(), DEPTH, 1.0)
    assert report.lead is lead, report.reason
    assert not (report.lead and report.accepted)
    assert ("worth a render where it ended" in report.reason) is lead


@pytest.mark.parametrize(
    ("box_shift", "inliers", "accepted"),
    [
        (1.5, 650, True),  # within the boxes' own error (2 px here: 3 x 0.5 px is less)
        (4.0, 650, False),  # leaves the boxes, the image only half behind it
        (4.0, 720, False),
        (4.0, 850, True),  # leaves the boxes, and the image vouches for it
        (25.0, 790, True),  # the boxes were wrong (the general model's), the image is sure
    ],
)
def test_a_fit_that_leaves_the_boxes_needs_the_images_firm_support(box_shift, inliers, accepted):
    report = dense_report(
        fit(0.5, 2.0, inliers, 600), start_pose(), DEPTH, 1.0, box_shift=box_shift
    )
    assert report.accepted is accepted, report.reason
    assert report.box_shift_px == box_shift
    if not accepted:
        assert "moved the boxes" in report.reason
        assert not report.render_again


def test_the_box_shift_is_the_rms_move_of_the_paired_boxes_edges():
    pairs = (
        FreeCorrespondence(
            detection=0, object="a", label="a", residual_px=0.5, predicted_box=(0, 0, 10, 10)
        ),
        FreeCorrespondence(
            detection=1, object="b", label="b", residual_px=0.5, predicted_box=(5, 5, 9, 9)
        ),
        FreeCorrespondence(detection=2, object="c", label="c", residual_px=0.5, predicted_box=None),
    )
    start = start_pose().model_copy(update={"correspondences": pairs})
    moved = {"a": (3.0, 0.0, 13.0, 10.0), "b": (5.0, 5.0, 9.0, 9.0), "c": (1.0, 1.0, 2.0, 2.0)}
    # a's edges move 3, 0, 3, 0; b's not at all; c has no start box: sqrt(18 / 8)
    assert box_shift_px(start, moved) == pytest.approx(1.5)
    assert box_shift_px(start, {"a": None, "b": None}) == 0.0


@pytest.mark.parametrize(
    ("shift", "inliers", "focal_fitted", "again"),
    [
        (0.5, 700, False, False),  # a near move: the render's silhouettes still hold
        (1.5, 700, False, True),  # beyond a tenth of the depth, edges left over: render again
        (1.5, 900, False, False),  # as far, but the edges all match: nothing to gain
        (0.7, 900, True, True),  # the focal length fitted: past REFIT_ZOOM of the depth
        (0.5, 900, True, False),
    ],
)
def test_a_fit_that_moved_the_camera_far_from_its_render_asks_for_another(
    shift, inliers, focal_fitted, again
):
    """:func:`worth_another_render`: a fit of the pose alone asks for a render at it once its
    camera moved more than ``REFIT_MOVE`` of the points' depth with less than ``REFIT_SHARE``
    of its points on the target's edges; with the focal length fitted, once it moved more than
    ``REFIT_ZOOM``. Turning the camera alone never does (the silhouettes stay)."""
    moved = replace(fit(shift, 0.0, inliers, 680), depth=DEPTH, focal_fitted=focal_fitted)
    turned = replace(fit(0.0, 20.0, 700, 680), depth=DEPTH, focal_fitted=focal_fitted)
    camera = free_pinhole_camera(START.model_copy(update={"fov_deg": 43.6}), 320, 240, 43.6)
    assert worth_another_render(moved, camera) is again
    assert not worth_another_render(turned, camera)


@pytest.mark.parametrize(
    ("zoom", "again"), [(1.04, False), (0.95, False), (1.07, True), (0.93, True)]
)
def test_a_focal_length_fitted_far_from_the_renders_asks_for_another(zoom, again):
    """With the focal length fitted, the camera where it was: another render once the focal
    length moved more than ``REFIT_ZOOM`` from the render's."""
    k = Intrinsics(400.0 * zoom, 400.0 * zoom, 160.0, 120.0)
    zoomed = replace(fit(0.0, 0.0, 900, 680), depth=DEPTH, focal_fitted=True, intrinsics=k)
    camera = free_pinhole_camera(START.model_copy(update={"fov_deg": 43.6}), 320, 240, 43.6)
    assert worth_another_render(zoomed, camera) is again


def test_the_box_slack_is_in_the_renders_pixels():
    """A photo ten times the render's film: its box edges may move ten times as many of its
    own pixels (the detector and the render see it at about the film's size)."""
    small = fit(0.5, 2.0, 720, 600)
    large = replace(small, intrinsics=Intrinsics(40.0, 40.0, 16.0, 12.0))  # the render's film
    assert not dense_report(small, start_pose(), DEPTH, 1.0, box_shift=10.0).accepted
    report = dense_report(large, start_pose(), DEPTH, 0.1, box_shift=10.0)
    assert report.accepted, report.reason
    assert not dense_report(large, start_pose(), DEPTH, 0.1, box_shift=30.0).accepted


@pytest.mark.parametrize(
    ("chance", "inliers", "start", "accepted", "said"),
    [
        (0.02, 700, 520, True, "refined"),  # a plain target: about the raw shares
        (0.55, 700, 520, False, "a random pose would leave 55%"),  # 0.33 above chance
        (0.55, 950, 900, True, "a random pose would leave 55%"),  # 0.89 above chance
        (0.55, 760, 500, False, "did not converge"),  # 0.47 above chance: most unexplained
    ],
)
def test_shares_are_taken_above_the_chance_of_an_edge_rich_target(
    chance, inliers, start, accepted, said
):
    """On a target where any pose leaves half its points on edges, 700 of 1000 is no longer
    most of them."""
    report = dense_report(fit(0.5, 2.0, inliers, start, chance=chance), start_pose(), DEPTH, 1.0)
    assert report.accepted is accepted, report.reason
    assert report.chance == chance
    assert said in report.reason


def bending(k1: float, sigma: float, bend_px: float, bounded: bool = False) -> RadialCheck:
    """A lens check at the start pose: ``k1`` ± ``sigma``, bending ``bend_px`` film pixels."""
    rotation = START.rotation().T
    return RadialCheck(
        k1=k1,
        sigma=sigma,
        bend_px=bend_px,
        inliers=900,
        bounded=bounded,
        rotation=rotation,
        translation=-rotation @ np.asarray(START.position),
        zoom=1.0,
    )


@pytest.mark.parametrize(
    ("check", "moved", "scale", "bends"),
    [
        (bending(-0.1, 0.005, 6.0), 0.0, 1.0, True),
        (bending(-0.1, 0.005, 6.0), 3.0, 1.0, False),  # the fit was not accepted
        (bending(-0.1, 0.005, 1.5), 0.0, 1.0, False),  # too slight a bend for the fit's pixels
        (bending(-0.1, 0.005, 3.0), 0.0, 2.0, False),  # 3 film pixels are 1.5 of the target's
        (bending(-0.1, 0.03, 6.0), 0.0, 1.0, False),  # k1 not sure enough
        (bending(-0.5, 0.005, 60.0, bounded=True), 0.0, 1.0, False),  # on its bound: no lens
    ],
    ids=["bends", "not-accepted", "slight", "enlarged-film", "loose", "bounded"],
)
def test_a_lens_check_bends_only_past_its_thresholds_on_an_accepted_fit(check, moved, scale, bends):
    f = replace(fit(moved, 0.0, 900, 800), radial=check)
    report = dense_report(f, start_pose(), DEPTH, scale)
    assert report.lens is not None
    assert report.lens.bends is bends
    assert report.lens.bend_px == pytest.approx(check.bend_px / scale)
    assert report.accepted is (moved == 0.0)
