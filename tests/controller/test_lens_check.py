"""A photo searched without its intrinsics whose edges bend as a distorting lens's
(:mod:`services.controller.lens_check`): the rule on its own, and a free search over faked
stages (:mod:`tests.controller.free_stages`) whose optimizer's fit says the edges bend."""

from __future__ import annotations

import pytest

from services.common.contracts.free import LensBend, PhotoIntrinsics
from services.controller.lens_check import lens_bent
from tests.controller.free_stages import FakeStages, run

BENT = LensBend(k1=-0.061, k1_sigma=0.0025, bend_px=16.5, inliers=730, bends=True)
STRAIGHT = LensBend(k1=-0.009, k1_sigma=0.0015, bend_px=0.8, inliers=1940, bends=False)


def test_no_fit_doubts_nothing():
    assert lens_bent(None) is None
    assert lens_bent("no dense refinement (the optimizer stayed away)") is None


def test_a_search_whose_edges_bend_keeps_its_pose_unconfirmed_and_says_what_to_give(
    tmp_path, detail
):
    """The same search is confirmed when the fit's edges are straight (as with no check), and
    ambiguous with the lens's figures and what to give when they bend."""
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
    assert pose.position[2] == pytest.approx(clear.free.pose.position[2] + 0.3)
    assert pose.intrinsics.source == "estimated"
    assert pose.intrinsics.distortion is not None
    assert pose.intrinsics.distortion.k1 == BENT.k1
    assert result.free.box_pose is not None
    assert result.free.box_pose.position != pose.position
    assert "the answer is the pose fitted with that k1" in result.reason
    assert "the photo's edges bend as a distorting lens's do" in result.reason
    assert "k1 at -0.061 ± 0.003" in result.reason
    assert "16.5 px" in result.reason
    assert "give the lens's distortion" in result.reason


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
