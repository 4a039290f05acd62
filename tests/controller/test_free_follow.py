"""A render that disagrees while its fit is accepted is followed by a render at the fit
(:func:`services.controller.free_iterations.worth_following`): the answer, the budget and
resumption, over faked stages (:mod:`tests.controller.free_stages`)."""

from __future__ import annotations

import math

import pytest

from tests.controller.free_stages import (
    FakeStages,
    FirstFitLeads,
    RefusesTheSecondFit,
    run,
    run_stored,
    stored,
)


@pytest.mark.parametrize(("max_iterations", "renders"), [(4, 2), (1, 1)])
def test_a_disagreeing_render_whose_fit_is_accepted_is_rendered_again_at_the_fit(
    tmp_path, detail, max_iterations, renders
):
    """The box pose's render disagrees (an object not where the target shows it), but the fit
    from it is accepted, and ends at the target's pose without leaving enough of its edges on
    the target's to agree by them: the search renders that pose, which agrees box by box, and
    confirms it, within its renders (with one only, the box pose stays unconfirmed)."""
    stages = FakeStages(detail, right=5, edges=(0, 5), inliers=600, meet=True)
    final = run(tmp_path, stages, max_iterations=max_iterations)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.renders == result.free.renders == stages.calls["render"] == renders
    (iteration,) = final.iterations
    if renders == 1:
        assert not result.confirmed
        assert not iteration.done
        return
    assert result.confirmed
    assert result.free.status == "found"
    assert iteration.done
    assert iteration.camera is not None
    assert iteration.camera.position == pytest.approx((5.0, -3.9, 5.0))  # the fit's render
    assert iteration.candidate_camera == stages.rendered[0][0]  # the candidate's own render
    assert iteration.candidate_camera.position == (0.0, -4.0, 5.0)
    assert iteration.reason.startswith("pose 1 of 1 at its dense fit (its own render disagreed)")
    assert "agrees with the target box by box" in iteration.reason
    # the answer is refined by the second render's fit; beside it the pose that render checked
    assert result.free.pose.position == pytest.approx((5.0, -3.8, 5.0))
    assert result.free.box_pose is not None
    assert result.free.box_pose.position == pytest.approx((5.0, -3.9, 5.0))
    assert "1 render(s) at a candidate's dense fit" in result.reason
    assert iteration.timings.render_ms > 0.0


@pytest.mark.parametrize(("max_iterations", "renders"), [(2, 2), (3, 3)])
def test_renders_at_a_fit_count_in_the_budget_of_the_refit(
    tmp_path, detail, max_iterations, renders
):
    """Every fit asks for one more render at its pose: a followed candidate's refit is made
    only while the search's renders allow it, the render at the fit counted."""
    stages = FakeStages(detail, right=5, edges=(0, 5), inliers=600, meet=True, refits=5)
    final = run(tmp_path, stages, max_iterations=max_iterations)
    result = final.result
    assert result is not None
    assert result.confirmed
    assert result.renders == stages.calls["render"] == renders
    assert (result.refit_timings is not None) is (renders == 3)


@pytest.mark.parametrize("lead", [True, False])
def test_a_fit_too_far_to_take_is_rendered_when_it_is_a_lead(tmp_path, detail, lead):
    """The box pose's render disagrees and its fit moved too far to be accepted: a ``lead``
    (the image vouches for where it ended) is rendered, and that render, agreeing box by box,
    confirms the pose; a fit that is merely rejected leaves the box pose unconfirmed after its
    one render."""
    stages = FirstFitLeads(detail, lead=lead, right=5, edges=(0, 5), inliers=600, meet=True)
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.renders == stages.calls["render"] == (2 if lead else 1)
    assert result.confirmed is lead
    if lead:
        assert result.free.status == "found"
        assert result.free.pose.position == pytest.approx((5.0, -3.8, 5.0))
        assert final.iterations[0].reason.startswith("pose 1 of 1 at its dense fit")
    else:
        assert result.free.pose.position == pytest.approx((0.0, -4.0, 5.0))


def test_a_followed_candidate_is_answered_at_the_pose_its_render_checked(tmp_path, detail):
    """The render at the candidate's fit agrees box by box, but the fit from that render is not
    accepted: the answer is the pose that render was made at, not the candidate's box pose
    (whose own render disagreed)."""
    stages = RefusesTheSecondFit(detail, right=5, edges=(0, 5), inliers=600, meet=True)
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.confirmed
    assert result.renders == 2
    assert result.free.pose.position == pytest.approx((5.0, -3.9, 5.0))
    assert "the box pose is kept: the dense fit moved the pose implausibly far" in result.reason


def test_a_resumed_search_answers_a_followed_candidate_at_the_pose_its_render_checked(
    tmp_path, detail
):
    """Resumed after recording an iteration rendered at its candidate's dense fit: the answer is
    the pose that render was made at (no fit to refine it by), not the candidate's box pose,
    whose own render disagreed. Unconfirmed: no lens was given, and no render is left to check
    one by."""
    first = RefusesTheSecondFit(detail, right=5, edges=(0, 5), inliers=600, meet=True)
    store = stored(tmp_path, first)
    run_stored(store, first)
    with store.database.write() as session:
        session.execute("UPDATE searches SET status = 'failed' WHERE id = ?", ("s1",))
    store.reopen("s1")
    again = RefusesTheSecondFit(detail, right=5, edges=(0, 5), inliers=600, meet=True)
    final = run_stored(store, again)
    assert final.status == "succeeded", final.error
    assert again.calls == {"scene": 1, "free-pose": 1}  # answered from its iterations
    (iteration,) = final.iterations
    assert iteration.candidate_camera is not None
    result = final.result
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert "not checked for a distorting lens" in result.reason
    assert result.free.pose.position == pytest.approx((5.0, -3.9, 5.0))
    # the focal length the render was made with: the first fit's (no intrinsics given)
    assert result.free.pose.intrinsics.fx_px == pytest.approx(390.0)
    assert result.free.pose.intrinsics.fov_deg == pytest.approx(
        2 * math.degrees(math.atan(160 / 390))
    )
