"""A hemisphere answer settled by the render's edges (:mod:`services.controller.grid_edges`):
the grid camera as a free pose, and the rule on its own (the loop's use of it is in
``test_runner.py``, a whole search through the real services in ``test_e2e.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.contracts.free import DenseReport
from services.common.contracts.optimize import GridPose, SearchableGrid
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.search import SearchResult
from services.common.geometry.camera import pinhole_camera
from services.common.geometry.free_camera import free_pinhole_camera
from services.common.geometry.pose import GridIndex, Pose
from services.controller.grid_edges import (
    BOUNDARY_SHARE,
    ON_SPHERE,
    STEEP_THETA_DEG,
    grid_free_pose,
    near_a_boundary,
    settled_result,
    steep,
)

GRID = SearchableGrid(angle_step_deg=7.5, min_theta_deg=7.5, max_theta_deg=82.5)
RADIUS, FOV, SIZE = 8.0, 45.0, (320, 240)


def _answer(index: GridIndex) -> SearchResult:
    at = GRID.grid().pose(index)
    return SearchResult(
        pose=GridPose(index=index, theta_deg=at.theta_deg, phi_deg=at.phi_deg),
        refined_pose=at,
        confidence=0.2,
        renders=1,
        ambiguous=True,
        confirmed=False,
        reason="not confirmed: the answer is ambiguous",
    )


def _outcome(at: Pose, *, scale: float = 1.0, **fit: object) -> RefinePoseResponse:
    """A fit that ended at hemisphere pose ``at``, its camera ``scale`` times the radius out."""
    pose = grid_free_pose(at, RADIUS * scale, FOV, SIZE)
    report = DenseReport(
        converged=True,
        accepted=True,
        reason="refined by the render's edges",
        edge_points=800,
        inliers=760,
        start_inliers=500,
        residual_px=0.5,
        focal_fitted=False,
        moved=1.0,
        moved_rotation_deg=7.0,
    )
    return RefinePoseResponse(pose=pose, fit=report.model_copy(update=fit))


@pytest.mark.parametrize(("theta", "phi"), [(30.0, 30.0), (67.5, 1.0), (7.5, 250.0)])
def test_the_grid_camera_as_a_free_pose_is_the_renderer_s_camera(theta, phi):
    pose = Pose(theta_deg=theta, phi_deg=phi)
    free = grid_free_pose(pose, RADIUS, FOV, SIZE)
    seen = free_pinhole_camera(free.camera(), *SIZE, FOV)
    grid = pinhole_camera(pose, RADIUS, FOV, *SIZE)
    np.testing.assert_allclose(seen.rotation, grid.rotation, atol=1e-9)
    np.testing.assert_allclose(seen.position, grid.position, atol=1e-9)
    assert (seen.fx, seen.cx, seen.cy) == pytest.approx((grid.fx, grid.cx, grid.cy))
    assert free.intrinsics.source == "scene"
    assert free.correspondences == ()


def test_a_fit_that_pins_the_camera_on_the_hemisphere_moves_the_answer():
    truth = GridIndex(lat=4, lon=5)
    on_grid = GRID.grid().pose(truth)
    ended = Pose(theta_deg=on_grid.theta_deg + 1.2, phi_deg=on_grid.phi_deg - 0.8)
    settled = settled_result(_answer(GridIndex(lat=3, lon=4)), _outcome(ended), GRID, RADIUS)
    assert settled.pose.index == truth
    assert settled.refined_pose.theta_deg == pytest.approx(ended.theta_deg)
    assert settled.refined_pose.phi_deg == pytest.approx(ended.phi_deg)
    assert settled.renders == 2
    assert not settled.confirmed
    assert settled.ambiguous
    assert "nearest lat 4 lon 5, not lat 3 lon 4 (not rendered there)" in settled.reason


def test_a_fit_that_stays_keeps_the_grid_pose_and_sharpens_the_direction():
    answer = _answer(GridIndex(lat=4, lon=5))
    ended = Pose(theta_deg=answer.pose.theta_deg - 0.3, phi_deg=answer.pose.phi_deg + 0.2)
    settled = settled_result(answer, _outcome(ended), GRID, RADIUS)
    assert settled.pose == answer.pose
    assert settled.refined_pose.theta_deg == pytest.approx(ended.theta_deg)
    assert settled.reason.endswith("nearest this grid pose")


@pytest.mark.parametrize(
    ("fit", "scale", "why"),
    [
        ({"accepted": False, "reason": "the dense fit did not converge"}, 1.0, "did not converge"),
        ({"inliers": 400}, 1.0, "400 of 800 edge points on the target's: too few to pin it"),
        ({"edge_points": 100, "inliers": 100}, 1.0, "too few to pin it"),
        ({}, 1.0 + 2 * ON_SPHERE, "off the hemisphere"),
        ({}, 1.0 - 2 * ON_SPHERE, "off the hemisphere"),
    ],
)
def test_a_fit_that_does_not_pin_the_camera_on_the_hemisphere_settles_nothing(fit, scale, why):
    answer = _answer(GridIndex(lat=3, lon=4))
    far = Pose(theta_deg=45.0, phi_deg=120.0)
    settled = settled_result(answer, _outcome(far, scale=scale, **fit), GRID, RADIUS)
    assert settled.pose == answer.pose
    assert settled.refined_pose == answer.refined_pose
    assert settled.renders == 2
    assert "the render's edges did not settle it (" in settled.reason
    assert why in settled.reason


def test_a_refinement_that_never_ran_settles_nothing():
    answer = _answer(GridIndex(lat=3, lon=4))
    settled = settled_result(answer, "no dense refinement (optimizer away)", GRID, RADIUS)
    assert settled.pose == answer.pose
    assert settled.renders == 2
    assert settled.reason.endswith("did not settle it (no dense refinement (optimizer away))")


def test_a_confirmed_answer_moved_by_the_edges_is_no_longer_confirmed():
    answer = _answer(GridIndex(lat=3, lon=4)).model_copy(
        update={"confirmed": True, "ambiguous": False, "reason": "the views agree"}
    )
    at = GRID.grid().pose(GridIndex(lat=4, lon=5))
    settled = settled_result(answer, _outcome(at), GRID, RADIUS)
    assert settled.pose.index == GridIndex(lat=4, lon=5)
    assert not settled.confirmed
    assert settled.reason.startswith("not confirmed: the render's edges put the camera at")
    assert settled.reason.endswith("the views had confirmed it: the views agree")
    kept = settled_result(answer, _outcome(GRID.grid().pose(GridIndex(lat=3, lon=4))), GRID, RADIUS)
    assert kept.confirmed
    assert kept.pose == answer.pose


@pytest.mark.parametrize(("offset", "near"), [(0.0, False), (2.0, False), (3.4, True), (3.7, True)])
def test_near_a_boundary_is_within_a_quarter_step_of_the_next_grid_pose(offset, near):
    """Lat 2 (θ 22.5°) and lat 3 (θ 30°) at φ 0°: an estimate ``offset`` from lat 2 towards
    lat 3 is nearer lat 3 than lat 2 by 7.5° − 2 · offset, under a quarter step (1.875°) past
    an offset of 2.81°."""
    answer = _answer(GridIndex(lat=2, lon=0))
    pose = answer.pose
    moved = Pose(theta_deg=pose.theta_deg + offset, phi_deg=pose.phi_deg)
    result = answer.model_copy(update={"refined_pose": moved})
    assert near_a_boundary(result, GRID) is near
    assert BOUNDARY_SHARE * GRID.angle_step_deg == pytest.approx(1.875)


@pytest.mark.parametrize(
    ("lat", "refined", "looks_down"),
    [(0, None, True), (2, None, True), (3, None, False), (3, 28.0, True), (5, 40.0, False)],
)
def test_steep_is_an_estimate_or_grid_pose_below_the_steep_theta(lat, refined, looks_down):
    """The grid's rings are 7.5° apart from 7.5°: lat 2 is θ 22.5°, lat 3 θ 30°."""
    answer = _answer(GridIndex(lat=lat, lon=0))
    if refined is not None:
        answer = answer.model_copy(update={"refined_pose": Pose(theta_deg=refined, phi_deg=0.0)})
    assert steep(answer) is looks_down
    assert STEEP_THETA_DEG == 30.0


def test_a_steep_confirmed_answer_the_edges_cannot_settle_is_no_longer_confirmed():
    """Looking down, the views hardly tell the rings apart: their confirmation stands only when
    the edges keep the answer; a refused fit, or no fit, unconfirms it (``vouch``), where an
    answer elsewhere keeps its confirmation."""
    answer = _answer(GridIndex(lat=1, lon=2)).model_copy(
        update={"confirmed": True, "ambiguous": False, "reason": "the views agree"}
    )
    refused = _outcome(Pose(theta_deg=45.0, phi_deg=120.0), inliers=300)
    for outcome in (refused, "no dense refinement (optimizer away)"):
        kept = settled_result(answer, outcome, GRID, RADIUS)
        assert kept.confirmed
        doubted = settled_result(answer, outcome, GRID, RADIUS, vouch=True)
        assert not doubted.confirmed
        assert doubted.pose == answer.pose
        assert doubted.renders == 2
        assert doubted.reason.startswith("not confirmed: looking 75° down, the views hardly tell")
        assert doubted.reason.endswith("the views had confirmed it: the views agree")
    held = settled_result(answer, _outcome(answer.refined_pose), GRID, RADIUS, vouch=True)
    assert held.confirmed
    assert held.pose == answer.pose
