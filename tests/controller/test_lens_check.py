"""A photo searched without its intrinsics whose edges bend as a distorting lens's
(:mod:`services.controller.lens_check`): the rules on their own, and a free search over faked
stages (:mod:`tests.controller.free_stages`) whose optimizer's fit says the edges bend: its lens
pose rendered through that lens and refitted from there."""

from __future__ import annotations

import pytest

from services.common.contracts.free import LensBend, PhotoIntrinsics
from services.common.contracts.refine import RefinePoseResponse
from services.controller.broker import BrokerError
from services.controller.lens_check import lens_bent, through_lens
from tests.controller.free_stages import (
    FakeStages,
    RefusesTheSecondFit,
    candidate,
    dense_report,
    run,
)

BENT = LensBend(k1=-0.061, k1_sigma=0.0025, bend_px=16.5, inliers=730, bends=True)
STRAIGHT = LensBend(k1=-0.009, k1_sigma=0.0015, bend_px=0.8, inliers=1940, bends=False)


def test_no_fit_doubts_nothing():
    assert lens_bent(None) is None
    assert lens_bent("no dense refinement (the optimizer stayed away)") is None


def test_a_search_whose_edges_bend_keeps_its_pose_unconfirmed_and_says_what_to_give(
    tmp_path, detail
):
    """The same search is confirmed when the fit's edges are straight (as with no check), and
    ambiguous with the lens's figures and what to give when they bend: its answer is then the
    lens pose of a fit from a render through the lens the first fit estimated (the fake's
    lens poses stand 0.3 above their fit's start: 0.6 above the pinhole's after both)."""
    straight = FakeStages(detail, inliers=850)
    straight.lens = STRAIGHT
    clear = run(tmp_path / "straight", straight).result
    assert clear is not None
    assert clear.confirmed
    assert clear.free is not None
    assert clear.free.dense is not None
    assert clear.free.dense.lens == STRAIGHT

    bent = FakeStages(detail, inliers=850)
    bent.lens = BENT
    final = run(tmp_path / "bent", bent)
    result = final.result
    assert final.status == "succeeded", final.error
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert result.ambiguous
    assert result.free.status == "ambiguous"
    pose = result.free.pose  # the lens check's, its k1 the lens; the pinhole's kept beside it
    assert pose.position[2] == pytest.approx(clear.free.pose.position[2] + 0.6)
    lensed, _ = bent.rendered[-1]  # the last render: through the first fit's lens
    assert lensed.distortion is not None
    assert lensed.distortion.k1 == BENT.k1
    again = bent.refinements[-1]
    assert again.fit_lens
    assert again.fit_focal  # no intrinsics given: the focal length is fitted with the lens
    assert result.renders == clear.renders + 1
    assert result.refit_timings is not None
    assert "refitted through the estimated lens by one more render" in result.reason
    assert pose.intrinsics.source == "estimated"
    assert pose.intrinsics.distortion is not None
    assert pose.intrinsics.distortion.k1 == BENT.k1
    assert result.free.box_pose is not None
    assert result.free.box_pose.position != pose.position
    assert "the answer is the pose fitted with that k1" in result.reason
    # the pinhole's fit leads the alternatives: either pose may be the right one
    assert result.free.alternatives[0].position == clear.free.pose.position
    assert result.free.alternatives[0].intrinsics.distortion is None
    assert "the photo's edges bend as a distorting lens's do" in result.reason
    assert "k1 at -0.061 ± 0.003" in result.reason
    assert "16.5 px" in result.reason
    assert "give the lens's distortion" in result.reason


def test_a_bend_whose_lens_explains_little_keeps_the_pinhole_pose_unconfirmed(tmp_path, detail):
    """A check that bends but whose ``k1`` removes little of the pinhole fit's misfit comes with
    no lens pose (the optimizer's rule: :func:`services.optimizer.lens_pose.lens_explains`): the
    answer stays at the pinhole's fit, is not confirmed, says why, and spends no render through
    a lens."""
    straight = FakeStages(detail, inliers=850)
    clear = run(tmp_path / "straight", straight).result
    assert clear is not None
    assert clear.free is not None

    faint = FakeStages(detail, inliers=850)
    faint.lens = BENT.model_copy(update={"k1": -0.11, "bend_px": 2.8, "cost_drop": 0.004})
    faint.lens_pose = False
    result = run(tmp_path / "faint", faint).result
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert result.free.status == "ambiguous"
    assert result.free.pose.position == clear.free.pose.position
    assert result.renders == clear.renders
    assert all(camera.distortion is None for camera, _ in faint.rendered)
    assert "the pinhole pose is kept (that k1 removes 0.4% of the pinhole fit's" in result.reason


def test_given_intrinsics_without_a_lens_are_doubted_too(tmp_path, detail):
    """A fov given without the lens is fitted as a pinhole's: its fit's check bends as well."""
    stages = FakeStages(detail, inliers=850)
    stages.lens = BENT
    final = run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    assert not any(r.fit_focal for r in stages.refinements)
    result = final.result
    assert result is not None
    assert not result.confirmed
    assert "bend as a distorting lens's do" in result.reason


def test_without_a_render_to_spare_the_first_lens_pose_answers(tmp_path, detail):
    """A search whose renders are spent makes none through the lens: the first fit's lens pose
    answers (0.3 above the pinhole's), unconfirmed all the same."""
    stages = FakeStages(detail, inliers=850)
    stages.lens = BENT
    result = run(tmp_path, stages, max_iterations=1).result
    assert result is not None
    assert len(stages.rendered) == 1
    assert not any(r.fit_lens for r in stages.refinements)
    assert result.free is not None
    assert result.free.box_pose is not None
    assert result.free.pose.position[2] == pytest.approx(result.free.box_pose.position[2] + 0.3)
    assert not result.confirmed
    assert "refitted through the estimated lens" not in result.reason


def test_a_refit_through_the_lens_that_is_not_accepted_leaves_the_first(tmp_path, detail):
    """The fit from the render through the lens is refused (moved too far): the first fit's
    lens pose answers, and the render it spent is counted."""
    stages = RefusesTheSecondFit(detail, inliers=850)
    stages.lens = BENT
    result = run(tmp_path, stages).result
    assert result is not None
    assert stages.refinements[-1].fit_lens
    assert result.free is not None
    assert result.free.box_pose is not None
    assert result.free.pose.position[2] == pytest.approx(result.free.box_pose.position[2] + 0.3)
    assert result.renders == 2
    assert not result.confirmed


def test_the_outcome_that_answers_a_bent_search():
    """The refit through the lens answers only when it was accepted and still bends."""
    first = _outcome(BENT, accepted=True)
    assert through_lens(first, "no dense refinement (the optimizer stayed away)") is first
    assert through_lens(first, _outcome(BENT, accepted=False)) is first
    assert through_lens(first, _outcome(STRAIGHT, accepted=True)) is first
    again = _outcome(BENT, accepted=True)
    assert through_lens(first, again) is again


def _outcome(lens: LensBend, accepted: bool) -> RefinePoseResponse:
    fit = dense_report(accepted=accepted, lens=lens)
    pose = candidate(1.0)
    return RefinePoseResponse(pose=pose, fit=fit, lens_pose=pose if lens.bends else None)


def test_a_render_through_the_lens_that_fails_leaves_the_first_lens_pose(tmp_path, detail):
    """No renderer left for the render through the lens (the outage policy's budget spent): the
    search still succeeds, answering the first fit's lens pose, unconfirmed; nothing is lost."""
    stages = FakeStages(
        detail, inliers=850, faults={"render": (1, BrokerError("renderer", "render", []))}
    )
    stages.lens = BENT
    final = run(tmp_path, stages)
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert stages.calls["render"] == 2
    assert not any(r.fit_lens for r in stages.refinements)
    assert result.free is not None
    assert result.free.box_pose is not None
    assert result.free.pose.position[2] == pytest.approx(result.free.box_pose.position[2] + 0.3)
    assert result.renders == 1
    assert not result.confirmed
    assert "the photo's edges bend as a distorting lens's do" in result.reason
    assert "refitted through the estimated lens" not in result.reason
