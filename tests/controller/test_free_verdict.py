"""Which rendered candidate answers and when it is confirmed (:mod:`services.controller.
free_verdict`, :mod:`services.controller.free_refine`): loose poses, rivals, unvouched fits,
EXIF focal lengths, edge evidence, over faked stages (:mod:`tests.controller.free_stages`)."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.contracts.free import (
    DenseReport,
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.search import (
    Iteration,
    StageTimings,
)
from services.controller.free_refine import edges_agree, edges_contradict, edges_pin
from services.controller.free_verdict import choice, others_standing
from tests.controller.free_stages import (
    FakeStages,
    candidate,
    run,
)


@pytest.mark.parametrize(
    ("ambiguity", "intrinsics", "inliers", "why"),
    [
        ("loose", PhotoIntrinsics(fov_deg=45.0), 850, None),  # pinned
        (
            "loose",
            PhotoIntrinsics(fx_px=386.0, fy_px=386.0, source="exif"),
            900,
            "no render can check the photo's EXIF focal length",
        ),
        # 0.89 of the edges: not enough
        ("loose", PhotoIntrinsics(fov_deg=45.0), 800, "its edges do not pin the pose"),
        # no intrinsics: distance trades against focal length
        ("loose", None, 850, "without the photo's intrinsics a render cannot pin the pose"),
        # rivals no render can settle without the intrinsics
        ("rivals", None, 900, "the alternatives explain its boxes too"),
        ("focal", PhotoIntrinsics(fov_deg=45.0), 900, "the scene camera's field of view was"),
    ],
    ids=["given", "exif-unchecked", "too-few-edges", "no-intrinsics", "rivals-unknown", "focal"],
)
def test_a_loose_pose_is_confirmed_only_when_known_intrinsics_and_its_edges_pin_it(
    tmp_path, detail, ambiguity, intrinsics, inliers, why
):
    """Two candidates, the first one right: its render agrees, box by box and by its edges;
    an unconfirmed one says ``why``, by why the boxes left it ambiguous."""
    pinned = why is None
    stages = FakeStages(detail, status="ambiguous", count=2, ambiguity=ambiguity, inliers=inliers)
    stages.source = "given" if intrinsics is None else intrinsics.source
    if intrinsics is None:
        stages.source = "scene" if ambiguity == "focal" else "estimated"
    final = run(tmp_path, stages, intrinsics=intrinsics)
    result = final.result
    assert result is not None
    assert result.renders == 1
    assert result.free is not None
    assert result.confirmed is pinned
    assert result.ambiguous is not pinned
    assert result.free.status == ("found" if pinned else "ambiguous")
    if pinned:
        assert result.free.alternatives == ()
        assert result.reason.startswith("found: the boxes")
        assert f"its edges pin the pose: {inliers} of 900" in result.reason
    else:
        assert [p.position[0] for p in result.free.alternatives] == [1.0]
        assert f"agrees with the target box by box, but {why}" in result.reason
        assert result.reason.count("not confirmed") == 1


@pytest.mark.parametrize("pitch", [30.0, 75.0])
def test_without_intrinsics_a_steep_view_says_the_image_cannot_tell_distance_from_focal(
    tmp_path, detail, pitch
):
    """Looking 60° down or more, a target's edges hardly tell distance from focal length
    (``benchmarks.focal_valley``): the answer says so, and what would decide."""
    stages = FakeStages(detail, status="ambiguous", count=2, ambiguity="loose", inliers=850)
    stages.source, stages.pitch = "estimated", pitch
    result = run(tmp_path, stages).result
    assert result is not None
    assert not result.confirmed
    assert "distance trades against focal length" in result.reason
    steep = "looking 75° down the image itself hardly tells them apart: give the photo's"
    assert (steep in result.reason) is (pitch == 75.0)


@pytest.mark.parametrize(
    ("edges", "max_iterations", "meet", "confirmed"),
    [
        ((0,), 4, False, True),  # the rivals' renders disagree: the one left is pinned
        ((0, 2), 4, False, False),  # rival 2 agrees by its edges too: a symmetric layout
        ((0, 2), 4, True, True),  # …but its fit ends at pose 1: one pose, not two
        ((0,), 2, False, False),  # the budget leaves a rival unrendered
    ],
    ids=["ruled-out", "two-agree", "two-meet", "rival-unchecked"],
)
def test_rivals_are_rendered_and_only_the_one_left_standing_is_confirmed(
    tmp_path, detail, edges, max_iterations, meet, confirmed
):
    """Three rival candidates, the first one right and agreeing by its edges, the intrinsics
    given."""
    stages = FakeStages(
        detail,
        status="ambiguous",
        count=3,
        ambiguity="rivals",
        edges=edges,
        inliers=900,
        meet=meet,
    )
    final = run(tmp_path, stages, max_iterations, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.renders == min(3, max_iterations)
    assert result.confirmed is confirmed
    assert result.free.status == ("found" if confirmed else "ambiguous")
    assert result.free.pose.position[0] == 0.0
    first, *rest = final.iterations
    assert first.agrees
    assert not first.done
    assert first.next_pose == rest[0].pose
    assert "its rivals are rendered next" in first.reason
    assert [it.agrees for it in rest] == [k in edges for k in range(1, len(rest) + 1)]
    if confirmed:
        assert result.free.alternatives == ()
        assert "2 rival pose(s) explained the boxes almost as well" in result.reason
        assert "its edges hold: 900 of 900" in result.reason
    else:
        assert "not confirmed" in result.reason
        assert [p.position[0] for p in result.free.alternatives][0] == (2.0 if 2 in edges else 1.0)
    if edges == (0, 2) and not meet:
        assert "and so do the renders at pose(s) 3" in result.reason


@pytest.mark.parametrize(
    ("dx", "turn_deg", "standing"),
    [(0.1, 0.0, False), (0.3, 0.0, True), (0.0, 0.8, False), (0.0, 1.5, True)],
)
def test_an_agreeing_rival_stands_unless_its_fit_ends_at_the_chosen_pose(
    detail, dx, turn_deg, standing
):
    """Radius 10: 2 % is 0.2 scene units; 1° the turn."""
    half = float(np.radians(turn_deg)) / 2
    chosen, rival = candidate(0.0), candidate(dx)
    rival = rival.model_copy(
        update={"quaternion_wxyz": (float(np.cos(half)), 0.0, 0.0, float(np.sin(half)))}
    )
    pose = nearest_grid_pose((0.0, -4.0, 5.0), detail.spec.search.grid())
    history = [
        Iteration(
            index=k,
            pose=pose,
            image_size=(320, 240),
            detections=(),
            timings=StageTimings(),
            agrees=True,
        )
        for k in range(2)
    ]
    found = others_standing(history, history[0], [chosen, rival], {}, radius=10.0)
    assert found == ((1,) if standing else ())


@pytest.mark.parametrize(
    ("inliers", "renders", "confirmed"),
    [(700, 1, False), (800, 1, False), (810, 3, True)],
    ids=["edges-short", "edges-agree-only", "edges-hold"],
)
def test_rivals_are_rendered_when_the_agreeing_renders_edges_hold(
    tmp_path, detail, inliers, renders, confirmed
):
    """0.78 of the render's edges on the target's (short of agreeing by them), or 0.89 (they
    agree, but wrong poses were confirmed so): its rivals' renders could not confirm it, and
    they are not made; it is answered, not confirmed. 0.9: they are, they disagree, and it is
    confirmed."""
    stages = FakeStages(detail, status="ambiguous", count=3, ambiguity="rivals", inliers=inliers)
    final = run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    result = final.result
    assert result is not None
    assert result.renders == renders
    assert result.confirmed is confirmed
    first = final.iterations[0]
    assert first.agrees
    assert first.done is not confirmed
    assert ("its rivals are rendered next" in first.reason) is confirmed
    if confirmed:
        assert f"its edges hold: {inliers} of 900" in result.reason


@pytest.mark.parametrize(
    ("turn", "inliers", "kept_box"),
    [
        (0.5, 610, False),  # a small turn needs no support
        (2.7, 610, True),  # turned 2.7° explaining 10 more of 900 edge points (600 before)
        (2.7, 720, False),  # 1.2 times the start's
        (2.7, 810, False),  # nine in ten of the render's
    ],
)
def test_a_confirmed_pose_the_fit_turned_with_little_support_keeps_its_box_pose(
    tmp_path, detail, turn, inliers, kept_box
):
    """The render agreed at the box pose; the dense fit turned it. Seen on the demo under
    another light: box poses 0.2 % off turned 2.7° and 4.3°, 3 % more edges explained, and
    confirmed there. Without the image's firm support the box pose, which the render checked,
    stays the confirmed answer."""
    stages = FakeStages(detail, inliers=inliers, turn=turn)
    final = run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.confirmed
    assert result.free.status == "found"
    assert result.free.alternatives == ()
    assert result.free.dense is not None
    assert result.free.dense.accepted
    if kept_box:
        assert result.free.pose.position == (0.0, -4.0, 5.0)  # the box pose
        assert result.free.box_pose is None
        assert (
            f"the box pose, which the render checked, is kept: the fit turned it {turn:.1f}°"
            in result.reason
        )
        assert f"600 → {inliers} of 900 edge points" in result.reason
    else:
        assert result.free.pose.position[1] == pytest.approx(-3.9)  # the fit's pose
        assert result.free.box_pose is not None


def test_an_exif_focal_length_never_confirms_the_pose(tmp_path, detail):
    """A unique pose whose render agrees, but from the photo's EXIF focal length: a wrong one
    moves the camera along its axis and the render agrees all the same."""
    stages = FakeStages(detail)
    stages.source = "exif"
    exif = PhotoIntrinsics(fx_px=386.0, fy_px=386.0, source="exif")
    final = run(tmp_path, stages, intrinsics=exif)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.renders == 1
    assert not result.confirmed
    assert result.ambiguous
    assert result.free.status == "ambiguous"
    assert result.free.pose.intrinsics.source == "exif"
    assert "no render can check the photo's EXIF focal length" in result.reason
    assert "give fov_deg or the intrinsics to confirm it" in result.reason


def test_with_no_fit_accepted_the_pose_whose_render_the_image_explains_best_is_chosen(
    tmp_path, detail
):
    """Neither render agrees and neither fit is accepted: the candidate whose own render left
    more of its edge points on the target's answers, though the other's boxes match better."""
    stages = FakeStages(detail, status="ambiguous", count=2, right=9)
    final = run(tmp_path, stages)
    first, second = final.iterations
    assert first.match is not None

    def fit(start_inliers: int) -> RefinePoseResponse:
        report = DenseReport(
            converged=False, accepted=False, reason="the dense fit did not converge",
            edge_points=900, inliers=start_inliers, start_inliers=start_inliers,
            residual_px=0.6, focal_fitted=False, moved=0.0, moved_rotation_deg=0.0,
        )  # fmt: skip
        return RefinePoseResponse(pose=candidate(0.0), fit=report)

    better_boxes = second.model_copy(
        update={"match": first.match.model_copy(update={"score": 0.9})}
    )
    worse_boxes = first.model_copy(update={"match": first.match.model_copy(update={"score": 0.2})})
    history = [worse_boxes, better_boxes]
    chosen, agreed = choice(history, {0: fit(450), 1: fit(270)})
    assert not agreed
    assert chosen.index == 0  # 0.5 of its edges on the target's against 0.3
    chosen, _ = choice(history, {0: fit(270), 1: fit(270)})
    assert chosen.index == 1  # as many: the boxes decide
    chosen, _ = choice(history, {})  # no fit at all (resumed): the boxes decide
    assert chosen.index == 1


@pytest.mark.parametrize(
    ("converged", "accepted", "start", "end", "contradicts"),
    [
        (False, False, 600, 300, True),  # did not converge, few edges at its end
        (False, False, 600, 500, False),  # did not converge, most edges at its end
        (True, False, 50, 550, True),  # converged far from a render that showed few edges
        (True, False, 400, 550, False),  # ... from one that showed many (another light)
        (True, True, 50, 850, False),  # accepted: the render's pose refined
    ],
)
def test_a_fit_contradicts_a_render_s_boxes_when_the_image_is_explained_elsewhere(
    converged, accepted, start, end, contradicts
):
    fit = DenseReport(
        converged=converged,
        accepted=accepted,
        reason="",
        edge_points=900,
        inliers=end,
        start_inliers=start,
        residual_px=0.4,
        focal_fitted=False,
        moved=30.0,
        moved_rotation_deg=90.0,
    )
    outcome = RefinePoseResponse(pose=candidate(0.0), fit=fit)
    assert edges_contradict(outcome) is contradicts
    assert not edges_contradict("the optimizer stayed away")


@pytest.mark.parametrize(("chance", "said"), [(0.0, True), (0.6, False)])
def test_edges_agree_and_pin_only_above_the_chance_of_an_edge_rich_target(chance, said):
    """900 of 1000 points on the target's edges pin a pose; not when a random pose would
    leave 600 there (above chance: 0.75)."""
    fit = DenseReport(
        converged=True,
        accepted=True,
        reason="",
        edge_points=1000,
        inliers=900,
        start_inliers=880,
        residual_px=0.4,
        focal_fitted=False,
        moved=0.1,
        moved_rotation_deg=0.5,
        chance=chance,
    )
    assert fit.share() == pytest.approx((0.9 - chance) / (1 - chance))
    outcome = RefinePoseResponse(pose=candidate(0.0), fit=fit)
    given = PhotoIntrinsics(fov_deg=40.0)
    assert edges_agree(outcome) is said
    assert (edges_pin(outcome, given, "loose") is not None) is said
    # a fit of too few edge points pins nothing, however many lie on the target's edges
    few = RefinePoseResponse(
        pose=candidate(0.0), fit=fit.model_copy(update={"edge_points": 100, "inliers": 97})
    )
    assert edges_pin(few, given, "loose") is None
    # a fit at the target's chance says nothing, and one below it contradicts
    assert fit.share(600) == pytest.approx(0.0 if chance else 0.6)
