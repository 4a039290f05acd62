"""The free search loop (:mod:`services.controller.free_loop`) over faked stages
(:mod:`tests.controller.free_stages`), as tests/controller/test_runner.py tests the hemisphere
one: a found pose confirmed by its render, an ambiguous one never confirmed, the next
alternative rendered when a render disagrees (within the render budget), the render detected
and refined at once, failures a user can act on, resumption, the film scaled to the view
width; and the free options of a submission."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest

from services.common.contracts.detect import Detection, DetectResponse
from services.common.contracts.free import (
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.search import (
    SearchOptions,
    ViewSettings,
)
from services.common.errors import ProblemDetails, UnprocessableError
from services.common.geometry.free_camera import LensDistortion
from services.controller.broker import BrokerError
from services.controller.form import photo_intrinsics
from services.controller.free_match import compare_view
from services.controller.stages import StageError
from tests.controller.free_stages import (
    BOXES,
    LABELS,
    MODEL,
    PNG,
    FakeStages,
    run,
    run_stored,
    stored,
)


def test_a_found_pose_whose_render_agrees_is_confirmed_after_one_render(tmp_path, detail):
    stages = FakeStages(detail)
    intrinsics = PhotoIntrinsics(fov_deg=45.0)
    final = run(tmp_path, stages, intrinsics=intrinsics)
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.confirmed
    assert not result.ambiguous
    assert result.renders == 1
    free = result.free
    assert free is not None
    assert free.status == "found"
    # the answer is the box pose refined by the same render, the box pose beside it
    assert free.pose.position == (0.0, -3.9, 5.0)
    assert free.box_pose is not None
    assert free.box_pose.position == (0.0, -4.0, 5.0)
    assert free.dense is not None
    assert free.dense.accepted
    assert "refined by the render's edges" in result.reason
    assert free.pose.intrinsics.source == "given"
    assert not stages.refinements[0].fit_focal
    assert stages.refinements[0].pose == free.box_pose
    assert free.match_rms_px == pytest.approx(0.0)
    assert free.nearest_grid == result.pose
    assert result.pose == nearest_grid_pose((0.0, -3.9, 5.0), detail.spec.search.grid())
    assert result.confidence == pytest.approx(0.9)
    # the optimizer was asked with the photo's intrinsics and the input size of the detector
    # that found its boxes; the render is the pose's camera
    assert stages.requests[0].intrinsics == intrinsics
    assert stages.requests[0].detector_input == MODEL.input_size
    (iteration,) = final.iterations
    assert iteration.done
    assert iteration.camera == stages.rendered[0][0]
    assert iteration.camera is not None
    assert iteration.camera.position == (0.0, -4.0, 5.0)
    assert stages.calls == {"scene": 1, "detect target": 1, "free-pose": 1, "render": 1,
                            "detect view": 1, "refine": 1, "target": 1}  # fmt: skip
    assert final.target_detections is not None
    assert final.target_model == MODEL


@pytest.mark.parametrize(("max_iterations", "renders", "y"), [(4, 2, -3.8), (1, 1, -3.9)])
def test_a_fit_that_asks_for_it_is_refitted_by_one_more_render(
    tmp_path, detail, max_iterations, renders, y
):
    """A fitted focal length far from the render's: one render more at the refined pose and
    a refit from there, when the search's renders allow; counted in its renders."""
    stages = FakeStages(detail, refits=5)
    final = run(tmp_path, stages, max_iterations=max_iterations)
    result = final.result
    assert result is not None
    assert result.free is not None
    assert result.confirmed
    assert result.renders == result.free.renders == renders
    assert stages.calls["render"] == renders
    assert result.free.pose.position == pytest.approx((0.0, y, 5.0))
    assert result.free.box_pose is not None
    assert result.free.box_pose.position == (0.0, -4.0, 5.0)
    if renders == 2:  # rendered at the first fit's pose, refitted from it, once only
        assert stages.rendered[1][0].position == pytest.approx((0.0, -3.9, 5.0))
        assert stages.refinements[1].pose.position == pytest.approx((0.0, -3.9, 5.0))
        assert "refitted by one more render" in result.reason
        # its milliseconds are the result's, not an iteration's
        assert result.refit_timings is not None
        assert result.refit_timings.render_ms > 0.0
        assert result.refit_timings.refine_ms > 0.0
    else:
        assert result.refit_timings is None
    assert len(final.iterations) == 1  # the refit render is not an iteration of the search


def test_a_refit_render_that_fails_leaves_the_first_fit_answering(tmp_path, detail):
    """No renderer left for the refit's render (the outage policy's budget spent): the search
    succeeds with its first fit, as if no refit had been asked for, rather than failing after
    its iterations (a retry would resume there, with no fit at all)."""
    faults = {"render": (1, BrokerError("renderer", "render", []))}
    stages = FakeStages(detail, refits=5, faults=faults)
    final = run(tmp_path, stages)
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.free is not None
    assert stages.calls["render"] == 2
    assert result.renders == 1
    assert result.refit_timings is None
    assert result.free.pose.position == pytest.approx((0.0, -3.9, 5.0))
    assert "refitted by one more render" not in result.reason


def test_a_found_pose_whose_render_disagrees_is_not_confirmed(tmp_path, detail):
    stages = FakeStages(detail, right=5)
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert not result.confirmed
    assert result.ambiguous
    assert result.free is not None
    assert result.free.status == "ambiguous"
    assert result.renders == 1
    assert result.reason.startswith("not confirmed: no render of the 1 pose(s) tried agreed")
    assert stages.calls["refine"] == 1  # its edges were fitted too, and disagreed
    assert result.free.dense is not None
    assert not result.free.dense.accepted
    assert result.free.pose.position == (0.0, -4.0, 5.0)  # the box pose is kept
    assert "300 of 900 edges on the target's" in final.iterations[0].reason


def test_a_render_whose_edges_agree_confirms_the_pose_though_its_boxes_disagree(tmp_path, detail):
    """The detector names the render's objects unlike the target's (say, the general model):
    the dense fit's edges still vouch for the pose, and it is refined by them."""
    stages = FakeStages(detail, right=5, edges=(0,))
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.confirmed
    assert result.renders == 1
    assert result.free is not None
    assert result.free.status == "found"
    assert result.free.pose.position == (0.0, -3.9, 5.0)
    assert "agrees with the target by its edges (its boxes disagree)" in result.reason
    (iteration,) = final.iterations
    assert iteration.done
    assert "but its edges agree: 800 of 900" in iteration.reason


def test_a_render_whose_boxes_agree_but_whose_edges_do_not_goes_on_to_the_next_pose(
    tmp_path, detail
):
    """A moved object can let a wrong pose pair every box: the dense fit from its render that
    leaves few edges on the target's overrules the boxes, and the next alternative is tried."""
    stages = FakeStages(detail, status="ambiguous", count=3, right=0, edges=(1,))
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.renders == 2
    assert not result.confirmed
    first, second = final.iterations
    assert not first.done
    assert "but its edges do not: 300 of 900" in first.reason
    assert second.done
    assert result.free is not None
    assert result.free.pose.position == (1.0, -3.9, 5.0)
    assert "agrees with the target by its edges (its boxes disagree)" in result.reason


def test_with_no_render_agreeing_the_pose_the_image_explains_best_is_answered(tmp_path, detail):
    """No render's boxes agree, and no fit leaves most of its render's edges on the target's:
    the candidate whose accepted fit explains the most edges answers, refined, ambiguous."""
    stages = FakeStages(detail, status="ambiguous", count=3, right=9, edges=(1,), inliers=600)
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    # the second candidate's accepted fit was rendered too (and disagreed): 4 renders, 3 poses
    assert result.renders == result.free.renders == stages.calls["render"] == 4
    assert [camera.position[0] for camera, _ in stages.rendered] == [0.0, 1.0, 1.0, 2.0]
    assert stages.rendered[2][0].position[1] == pytest.approx(-3.9)
    assert "1 render(s) at a candidate's dense fit" in result.reason
    assert len(final.iterations) == 3
    assert all(it.candidate_camera is None for it in final.iterations)  # each shows its own
    assert not result.confirmed
    assert result.free is not None
    assert result.free.status == "ambiguous"
    assert result.free.pose.position == (1.0, -3.9, 5.0)
    assert result.free.box_pose is not None
    assert result.free.box_pose.position == (1.0, -4.0, 5.0)
    assert "the best was pose 2" in result.reason
    assert [it.done for it in final.iterations] == [False, False, False]


def test_without_intrinsics_the_refined_focal_length_is_the_estimate(tmp_path, detail):
    stages = FakeStages(detail)
    final = run(tmp_path, stages)
    assert final.result is not None
    free = final.result.free
    assert free is not None
    assert stages.refinements[0].fit_focal
    assert free.pose.intrinsics.source == "estimated"
    assert free.pose.intrinsics.fx_px == 390.0


@pytest.mark.parametrize(
    ("refine", "said"),
    [
        ("rejected", "the box pose is kept: the dense fit moved the pose implausibly far"),
        (
            StageError("optimizer", ProblemDetails(title="No", status=422, detail="bad render")),
            "no dense refinement (the optimizer refused a task: bad render): the box pose",
        ),
    ],
    ids=["rejected", "refused"],
)
def test_a_refinement_not_accepted_keeps_the_box_pose_and_says_so(tmp_path, detail, refine, said):
    stages = FakeStages(detail, refine=refine)
    final = run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.confirmed
    assert result.renders == 1
    assert result.free is not None
    assert result.free.pose.position == (0.0, -4.0, 5.0)
    assert result.free.box_pose is None
    assert said in result.reason


def test_an_ambiguous_answer_renders_the_next_alternative_and_is_never_confirmed(tmp_path, detail):
    stages = FakeStages(detail, status="ambiguous", count=3, right=1)
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.renders == 2
    assert not result.confirmed
    assert result.ambiguous
    free = result.free
    assert free is not None
    assert free.status == "ambiguous"
    assert free.pose.position[0] == 1.0
    assert sorted(p.position[0] for p in free.alternatives) == [0.0, 2.0]
    first, second = final.iterations
    assert not first.done
    assert second.done
    assert first.next_pose == second.pose
    assert "alternatives explain its boxes too" in result.reason


def test_the_render_budget_bounds_the_alternatives_tried(tmp_path, detail):
    stages = FakeStages(detail, status="ambiguous", count=4, right=9)
    final = run(tmp_path, stages, max_iterations=2)
    assert final.result is not None
    assert final.result.renders == 2
    assert stages.calls["render"] == 2
    assert not final.result.confirmed
    assert final.iterations[-1].next_pose is None


def test_no_detection_in_the_target_fails_with_what_to_do(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, boxes=()))
    assert final.status == "failed"
    assert final.error is not None
    assert final.error.type == "urn:cosmos:problem:no-target-objects"
    assert "at least 3" in (final.error.detail or "")
    assert final.target_detections == ()


def test_no_pose_fails_with_the_optimizer_s_reason(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, status="failed"))
    assert final.status == "failed"
    assert final.error is not None
    assert final.error.type == "urn:cosmos:problem:no-free-pose"
    assert final.error.detail == "failed: no detection names"
    assert final.target_detections is not None
    assert len(final.target_detections) == 3


def test_an_interrupted_free_search_resumes_with_the_next_alternative(tmp_path, detail):
    first = FakeStages(
        detail, status="ambiguous", count=3, right=2,
        faults={"render": (2, asyncio.CancelledError())},
    )  # fmt: skip
    store = stored(tmp_path, first)
    with pytest.raises(asyncio.CancelledError):
        run_stored(store, first)
    interrupted = store.get("s1")
    assert interrupted is not None
    assert [it.index for it in interrupted.iterations] == [0, 1]
    assert interrupted.target_detections is not None
    again = FakeStages(detail, status="ambiguous", count=3, right=2)
    final = run_stored(store, again)
    assert final.status == "succeeded", final.error
    assert again.calls["detect target"] == 0
    assert again.calls["render"] == 1
    assert again.requests[0].detector_input == MODEL.input_size  # the recorded target's model
    assert [it.index for it in final.iterations] == [0, 1, 2]
    assert final.result is not None
    assert final.result.renders == 3
    assert final.result.free is not None
    assert final.result.free.pose.position[0] == 2.0
    assert final.result.free.status == "ambiguous"  # refined, and still ambiguous
    assert final.result.free.dense is not None
    assert final.result.free.dense.accepted
    assert not final.result.confirmed


def test_a_large_photo_is_rendered_at_the_view_width_with_its_intrinsics_scaled(tmp_path, detail):
    stages = FakeStages(detail, target_size=(640, 480))
    intrinsics = PhotoIntrinsics(fov_deg=45.0)
    final = run(tmp_path, stages, view_settings=ViewSettings(width=160), intrinsics=intrinsics)
    assert final.result is not None
    assert final.result.confirmed
    camera, size = stages.rendered[0]
    assert size == (160, 120)
    assert camera.fx_px == pytest.approx(386.0 / 4)
    assert camera.cx_px == pytest.approx(40.0)


@pytest.mark.parametrize(
    ("width", "photo", "film"),
    [
        (160, (640, 480), (320, 240)),
        (480, (640, 480), (960, 720)),  # up to twice the photo
        (320, (320, 240), (640, 480)),  # a photo as small as the views: twice its size
        (640, (400, 300), (800, 600)),  # no wider than twice the photo
        (800, (4000, 3000), (1280, 960)),  # nor than FOCAL_VIEW_MAX_WIDTH
        (1600, (4000, 3000), (1600, 1200)),  # unless the view width is
    ],
)
def test_without_intrinsics_the_views_are_twice_the_view_width_and_at_most_twice_the_photo(
    tmp_path, detail, width, photo, film
):
    """The focal length is fitted on the renders' edges: a search not given it renders them
    twice the view width wide, never wider than twice the photo (its grey is enlarged to the
    film) nor 1280 pixels."""
    stages = FakeStages(detail, target_size=photo)
    final = run(tmp_path, stages, view_settings=ViewSettings(width=width))
    assert final.status == "succeeded", final.error
    camera, size = stages.rendered[0]
    assert size == film
    assert camera.fx_px == pytest.approx(386.0 * film[0] / photo[0])
    ((prepared, _),) = stages.prepared
    assert prepared.film == film


@pytest.mark.parametrize("given", [True, False])
def test_the_target_is_made_ready_for_the_refinements_on_the_renders_film(tmp_path, detail, given):
    """Before any refinement, the optimizer is asked to make the target ready on the film the
    renders are made on, every level of its maps when the focal length will be fitted."""
    stages = FakeStages(detail, target_size=(640, 480))
    intrinsics = PhotoIntrinsics(fov_deg=45.0) if given else None
    final = run(tmp_path, stages, view_settings=ViewSettings(width=160), intrinsics=intrinsics)
    assert final.status == "succeeded", final.error
    ((request, refinements_before),) = stages.prepared
    assert request.film == stages.rendered[0][1] == ((160, 120) if given else (320, 240))
    assert request.fit_focal is not given
    assert refinements_before == 0


def test_a_target_the_optimizer_could_not_make_ready_changes_nothing(tmp_path, detail):
    """Making the target ready is best effort: refused, or with the optimizer away, the
    search runs as it would have, each refinement making the target's maps itself."""
    problem = ProblemDetails(title="No", status=422, detail="bad film")
    answers = []
    for faults in (
        {},
        {"target": (0, StageError("optimizer", problem))},
        {"target": (0, OSError())},
    ):
        stages = FakeStages(detail, faults=faults)
        final = run(tmp_path / str(len(answers)), stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
        assert final.status == "succeeded", final.error
        assert final.result is not None
        answers.append(final.result.model_dump(exclude={"timings"}))
        assert stages.calls["target"] == 1
    assert answers[1] == answers[0]
    assert answers[2] == answers[0]


def test_compare_view_pairs_by_label_within_the_gate():
    target = [Detection(label=label, class_id=0, confidence=0.9, box=box)
              for label, box in zip(LABELS, BOXES, strict=True)]  # fmt: skip
    close = [d.model_copy(update={"box": tuple(v + 1.0 for v in d.box)}) for d in target]
    check = compare_view(target, (320, 240), [0, 1, 2], close, (320, 240))
    assert check.agree
    assert check.match.rms_px == pytest.approx(1.0)
    assert check.match.pairs == 3
    swapped = [close[0].model_copy(update={"label": "green"}), *close[1:]]
    check = compare_view(target, (320, 240), [0, 1, 2], swapped, (320, 240))
    assert not check.agree
    assert check.missing == (0,)
    assert check.match.unpaired_current == pytest.approx(0.9)


def test_compare_view_takes_the_paired_object_s_name_for_a_mislabelled_detection():
    """The target's ``green`` box that the pose paired with ``red`` (its colour said so) is seen
    again where the render's detector names it ``red``; nor by any other name."""
    target = [Detection(label=label, class_id=0, confidence=0.9, box=box)
              for label, box in zip(("green", "green", "blue"), BOXES, strict=True)]  # fmt: skip
    view = [d.model_copy(update={"label": label}) for d, label in zip(target, LABELS, strict=True)]
    names = ("red", "green", "blue")
    assert compare_view(target, (320, 240), [0, 1, 2], view, (320, 240), names).agree
    assert compare_view(target, (320, 240), [0, 1, 2], view, (320, 240)).missing == (0,)
    renamed = [view[0].model_copy(update={"label": "blue"}), *view[1:]]
    check = compare_view(target, (320, 240), [0, 1, 2], renamed, (320, 240), names)
    assert check.missing == (0,)


@pytest.mark.parametrize(
    ("fields", "field"),
    [
        ({"fov_deg": "50"}, "fov_deg"),  # not a free search
        ({"mode": "free", "fov_deg": "50", "intrinsics": "300,300,160,120"}, "intrinsics"),
        ({"mode": "free", "distortion": "0.1,0,0,0"}, "distortion"),
        ({"mode": "free", "intrinsics": "0,300,160,120"}, "intrinsics"),
        ({"mode": "free", "intrinsics": "1e999,300,160,120"}, "intrinsics"),
        ({"mode": "free", "fov_deg": "50", "distortion": "5000,0,0,0"}, "distortion"),
        ({"mode": "free", "fov_deg": "50", "distortion": "0,0,0,0,5000"}, "distortion"),
    ],
)
def test_bad_free_options_name_their_field(fields, field):
    options = SearchOptions.model_validate({"scene": "demo", **fields})
    with pytest.raises(UnprocessableError) as raised:
        photo_intrinsics(options)
    assert raised.value.field == field


def test_free_options_give_the_photo_s_intrinsics():
    options = SearchOptions.model_validate(
        {"scene": "demo", "mode": "free", "intrinsics": "300, 310,160.5,120", "distortion":
         "-0.1,0.01,0,0"}
    )  # fmt: skip
    intrinsics = photo_intrinsics(options)
    assert intrinsics is not None
    assert (intrinsics.fx_px, intrinsics.fy_px, intrinsics.cx_px) == (300.0, 310.0, 160.5)
    assert intrinsics.distortion is not None
    assert intrinsics.distortion.k1 == -0.1
    assert intrinsics.distortion.k3 == 0.0
    with_k3 = options.model_dump() | {"distortion": "-0.1,0.01,0,0,-0.002"}
    lens = photo_intrinsics(SearchOptions.model_validate(with_k3))
    assert lens is not None
    assert lens.distortion == LensDistortion(k1=-0.1, k2=0.01, k3=-0.002)
    free = SearchOptions.model_validate({"scene": "demo", "mode": "free"})
    assert photo_intrinsics(free) is None


@pytest.mark.anyio
async def test_a_free_search_is_taken_with_its_intrinsics(controller):
    app, client = controller
    response = await client.post(
        "/searches",
        params={"scene": "demo", "mode": "free", "fov_deg": "50"},
        content=PNG_IMAGE,
        headers={"Content-Type": "image/png"},
    )
    assert response.status_code == 202, response.text
    body = response.json()
    assert body["mode"] == "free"
    assert body["intrinsics"]["fov_deg"] == 50.0
    bad = await client.post(
        "/searches",
        params={"scene": "demo", "mode": "free", "intrinsics": "1,2,3"},
        content=PNG_IMAGE,
        headers={"Content-Type": "image/png"},
    )
    assert bad.status_code == 422
    assert bad.json()["field"] == "intrinsics"


def _png() -> bytes:
    ok, data = cv2.imencode(".png", np.zeros((24, 32, 3), np.uint8))
    assert ok
    return bytes(data)


PNG_IMAGE = _png()


@pytest.mark.parametrize("lens", [None, LensDistortion(k1=-0.1)], ids=["no-lens", "lens-given"])
def test_a_free_search_resumed_after_its_agreeing_render_answers_it(tmp_path, detail, lens):
    """Answered from its iterations, with no render to fit by: the box pose, confirmed only
    when the search had its lens (no lens check was made)."""
    first = FakeStages(detail)
    given = PhotoIntrinsics(fov_deg=45.0, distortion=lens)
    store = stored(tmp_path, first, intrinsics=given)
    run_stored(store, first)
    done = store.get("s1")
    assert done is not None
    assert done.result is not None
    assert done.result.confirmed
    # as if the run had stopped after recording its last iteration, before its result
    with store.database.write() as session:
        session.execute("UPDATE searches SET status = 'failed' WHERE id = ?", ("s1",))
    store.reopen("s1")
    again = FakeStages(detail)
    final = run_stored(store, again)
    assert final.status == "succeeded", final.error
    assert again.calls == {"scene": 1, "free-pose": 1}  # answered from its iterations
    # no render to refine by: the box pose, saying so
    assert final.result is not None
    assert final.result.free is not None
    assert done.result.free is not None
    assert final.result.free.pose == done.result.free.box_pose
    assert "no dense refinement (resumed after its render)" in final.result.reason
    assert final.result.confirmed is (lens is not None)
    if lens is None:
        assert final.result.free.status == "ambiguous"
        assert "not checked for a distorting lens" in final.result.reason


class Overlapping(FakeStages):
    """Says when the view's detection (50 ms) and the dense fit (``fit_s``) start and end."""

    def __init__(self, *args, fit_s: float = 0.01, **kwargs):
        super().__init__(*args, **kwargs)
        self.fit_s = fit_s
        self.order: list[str] = []

    async def detect(self, image, media_type, request_id="", scene=None) -> DetectResponse:
        if image != PNG:
            self.order.append("detect starts")
            await asyncio.sleep(0.05)
            self.order.append("detect ends")
        return await super().detect(image, media_type, request_id, scene)

    async def refine_pose(self, request, target, render, request_id="") -> RefinePoseResponse:
        self.order.append("fit starts")
        await asyncio.sleep(self.fit_s)
        self.order.append("fit ends")
        return await super().refine_pose(request, target, render, request_id)


def test_the_render_is_detected_and_refined_at_once(tmp_path, detail):
    stages = Overlapping(detail)
    final = run(tmp_path, stages)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed
    assert stages.order == ["detect starts", "fit starts", "fit ends", "detect ends"]


@pytest.mark.parametrize("fit_s", [0.01, 0.12])
def test_an_iteration_times_its_dense_fit_beside_its_detection(tmp_path, detail, fit_s):
    """The fit's own milliseconds, whether it ends before the view's detection (50 ms) or
    after; the iteration's total counts the longer of the two."""
    final = run(tmp_path, Overlapping(detail, fit_s=fit_s))
    assert final.status == "succeeded", final.error
    timings = final.iterations[0].timings
    assert timings.detect_ms >= 50.0
    assert timings.refine_ms >= fit_s * 1000
    # the fit's own time, not the wait for the detection that ran beside it
    assert (timings.refine_ms < timings.detect_ms) == (fit_s < 0.05)
    slower = max(timings.detect_ms, timings.refine_ms)
    assert timings.total_ms == pytest.approx(timings.render_ms + slower + timings.optimize_ms)


def test_a_view_the_detector_refuses_fails_the_search_and_stops_its_fit(tmp_path, detail):
    problem = ProblemDetails(
        type="urn:cosmos:problem:bad-request", title="Bad request", status=422, detail="too big"
    )
    stages = Overlapping(
        detail, fit_s=1.0, faults={"detect view": (0, StageError("detector", problem))}
    )
    final = run(tmp_path, stages)
    assert final.status == "failed"
    assert final.error is not None
    assert "too big" in (final.error.detail or "")
    assert final.iterations == ()
    assert stages.order == ["detect starts", "fit starts", "detect ends"]  # the fit cancelled
