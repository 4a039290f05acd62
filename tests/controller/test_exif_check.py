"""A focal length from the photo's EXIF checked by its render's edges
(:mod:`services.controller.exif_check`): the rule on its own, and a free search over faked
stages (:mod:`tests.controller.free_stages`) whose optimizer answers a focal check."""

from __future__ import annotations

import pytest

from services.common.contracts.free import PhotoIntrinsics
from services.common.contracts.refine import FocalCheck, RefinePoseResponse
from services.controller.exif_check import CHECK_SIGMA, DISAGREE, exif_overruled
from tests.controller.free_stages import FakeStages, candidate, dense_report, run

EXIF = PhotoIntrinsics(fx_px=386.0, fy_px=386.0, source="exif")


def checked(off: float, **fit: object) -> RefinePoseResponse:
    """A refinement with the stated 386 px and a check ``off`` that share of it, whose fit
    says ``fit`` (else: accepted, focal fitted at 0.2 %, 850 of 900 edge points)."""
    report = dense_report()
    pose = candidate(0.0, source="exif")
    k = pose.intrinsics.model_copy(
        update={"fx_px": 386.0 * (1 + off), "fy_px": 386.0 * (1 + off), "source": "estimated"}
    )
    check_fit = report.model_copy(update={"focal_fitted": True, "focal_sigma": 0.002, **fit})
    check = FocalCheck(pose=pose.model_copy(update={"intrinsics": k}), fit=check_fit)
    return RefinePoseResponse(pose=pose, fit=report, focal_check=check)


@pytest.mark.parametrize(
    ("off", "fit", "overrules"),
    [
        (-0.12, {}, True),
        (0.05, {}, True),
        (DISAGREE * 0.9, {}, False),  # within rounding and fit error
        (-DISAGREE * 0.9, {}, False),
        (-0.12, {"focal_sigma": CHECK_SIGMA * 2}, False),  # the edges leave it loose
        (-0.12, {"focal_fitted": False, "focal_sigma": None}, False),
        (-0.12, {"accepted": False}, False),
        (-0.12, {"inliers": 700}, False),  # 0.78 of the edge points: too few
    ],
    ids=["short", "long", "agrees", "agrees-short", "loose", "not-fitted", "refused", "few"],
)
def test_the_check_overrules_the_exif_only_when_the_edges_pin_another_focal_length(
    off, fit, overrules
):
    outcome = checked(off, **fit)
    assert (exif_overruled(outcome) is not None) is overrules


def test_no_check_no_overruling():
    outcome = checked(-0.12).model_copy(update={"focal_check": None})
    assert exif_overruled(outcome) is None
    assert exif_overruled("no dense refinement (the optimizer stayed away)") is None
    assert exif_overruled(None) is None


def test_a_search_whose_edges_overrule_its_exif_answers_their_focal_length(tmp_path, detail):
    """The optimizer's check puts the focal length 12 % shorter than the EXIF's: the answer is
    the check's pose with its focal length estimated, not confirmed, and says why."""
    stages = FakeStages(detail, inliers=850)
    stages.source = "exif"
    stages.focal_check = -0.12
    final = run(tmp_path, stages, intrinsics=EXIF)
    assert all(r.check_focal and not r.fit_focal for r in stages.refinements)
    assert all(request.fit_focal for request, _ in stages.prepared)  # every level made ready
    result = final.result
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert result.ambiguous
    assert result.free.status == "ambiguous"
    pose = result.free.pose
    assert pose.intrinsics.source == "estimated"
    assert pose.intrinsics.fx_px == pytest.approx(386.0 * 0.88)
    assert pose.position[0] == pytest.approx(0.5)  # the check's pose
    assert result.free.box_pose is not None
    assert "do not bear out the photo's EXIF focal length" in result.reason
    assert "12.0% shorter" in result.reason
    assert result.renders == 1


def test_a_search_whose_edges_agree_with_its_exif_keeps_it_unconfirmed(tmp_path, detail):
    stages = FakeStages(detail, inliers=850)
    stages.source = "exif"
    stages.focal_check = 0.01
    final = run(tmp_path, stages, intrinsics=EXIF)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert result.free.pose.intrinsics.source == "exif"
    assert "no render can check the photo's EXIF focal length" in result.reason
    assert "bear out" not in result.reason


def test_given_intrinsics_are_not_checked(tmp_path, detail):
    stages = FakeStages(detail, inliers=850)
    stages.focal_check = -0.12
    run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    assert stages.refinements
    assert not any(r.check_focal for r in stages.refinements)
    assert not any(request.fit_focal for request, _ in stages.prepared)
