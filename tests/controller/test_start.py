"""A search's first pose (services.controller.start) with fake stages: without a given start the
target is detected first and the search starts where the optimizer predicts, ending after one
render when that view matches, also when the prediction is unsure (its best pose is still the
likeliest); a prediction without a pose or a refused one falls back to the drawn start;
a given start keeps the paper's protocol; an answer the search finds ambiguous is never
confirmed."""

from __future__ import annotations

import pytest

from services.common.contracts.optimize import NextPoseRequest, NextPoseResponse
from services.common.contracts.search import Search
from services.common.contracts.start_pose import StartPoseRequest, StartPoseResponse
from services.common.errors import ProblemDetails
from services.common.geometry.pose import GridIndex
from services.controller.stages import StageError
from services.controller.store import SearchStore, open_store, utcnow
from tests.controller.test_runner import OWN, PNG, FakeStages, run_stored

DRAWN = GridIndex(lat=3, lon=0)
TRUTH = GridIndex(lat=5, lon=7)


class StartStages(FakeStages):
    """:class:`FakeStages` whose optimizer predicts ``predicted`` with ``status`` and says done
    (``ambiguous`` as asked) at :data:`TRUTH` only; ``order`` lists the calls as made."""

    def __init__(self, *args, status="found", predicted=TRUTH, ambiguous=False, **kwargs):
        super().__init__(*args, **kwargs)
        self.status = status
        self.predicted = predicted
        self.ambiguous = ambiguous
        self.order: list[str] = []
        self.start_requests: list[StartPoseRequest] = []

    def _call(self, name: str) -> None:
        self.order.append(name)
        super()._call(name)

    async def start_pose(
        self, request: StartPoseRequest, request_id: str = ""
    ) -> StartPoseResponse:
        self._call("start pose")
        self.start_requests.append(request)
        return StartPoseResponse(
            status=self.status,
            pose=None if self.predicted is None else self.grid_pose(self.predicted),
            score=0.1,
            rms_px=0.5,
            pairs=1,
            reason="predicted" if self.status == "found" else f"{self.status}: because",
        )

    async def optimize(self, request: NextPoseRequest, request_id: str = "") -> NextPoseResponse:
        here = request.history[-1].pose
        self.done_after = 1 if (here.lat, here.lon) == (TRUTH.lat, TRUTH.lon) else 99
        answer = await super().optimize(request, request_id)
        if not answer.done:
            return answer
        reason = "the current view matches the target"
        if self.ambiguous:
            reason += "; ambiguous: 1 distant pose(s) explain the target almost as well"
        return answer.model_copy(update={"ambiguous": self.ambiguous, "reason": reason})


def stored(tmp_path, stages: FakeStages, *, start: GridIndex = DRAWN, given: bool) -> SearchStore:
    """A store holding search ``s1`` as submitted, its start ``given`` or drawn."""
    store = open_store(f"sqlite:///{tmp_path}/c.sqlite3")
    now = utcnow()
    store.create(
        Search(
            id="s1",
            status="queued",
            scene="demo",
            strategy="reprojection",
            start=stages.grid_pose(start),
            start_given=given,
            seed=1,
            max_iterations=6,
            created_at=now,
            updated_at=now,
            target_size=(320, 240),
        ),
        PNG,
    )
    return store


def test_without_a_start_the_predicted_view_ends_the_search_after_one_render(tmp_path, detail):
    stages = StartStages(detail)
    final = run_stored(stored(tmp_path, stages, given=False), stages)
    assert final.status == "succeeded", final.error
    assert [it.pose.index for it in final.iterations] == [TRUTH]
    assert final.result is not None
    assert final.result.renders == 1
    assert final.result.confirmed
    # the target first (its detections make the prediction), then the one view
    assert stages.order[1:5] == ["detect target", "start pose", "render", "detect view"]
    assert stages.calls["detect target"] == 1
    assert final.target_detections  # recorded with the first iteration
    assert stages.start_requests[0].object_classes is None  # the general model's shapes


def test_the_scene_s_own_model_asks_with_its_object_classes(tmp_path, detail):
    stages = StartStages(detail, models=(OWN, OWN))
    run_stored(stored(tmp_path, stages, given=False), stages)
    classes = stages.start_requests[0].object_classes
    assert classes is not None
    assert classes[0].label == "red"


@pytest.mark.parametrize("status", ["ambiguous", "failed"])
def test_an_unsure_prediction_still_starts_at_its_best_pose(tmp_path, detail, status):
    stages = StartStages(detail, status=status)
    final = run_stored(stored(tmp_path, stages, given=False), stages)
    assert final.status == "succeeded", final.error
    assert [it.pose.index for it in final.iterations] == [TRUTH]
    assert stages.calls["detect target"] == 1  # detected once, for the prediction


def test_a_prediction_without_a_pose_falls_back_to_the_drawn_start(tmp_path, detail):
    stages = StartStages(detail, status="failed", predicted=None)
    final = run_stored(stored(tmp_path, stages, given=False), stages)
    assert final.status == "succeeded", final.error
    assert final.iterations[0].pose.index == DRAWN


def test_an_optimizer_that_refuses_the_prediction_does_not_fail_the_search(tmp_path, detail):
    refusal = StageError("optimizer", ProblemDetails(title="Not Found", status=404))
    stages = StartStages(detail, faults={"start pose": (0, refusal)})
    final = run_stored(stored(tmp_path, stages, given=False), stages)
    assert final.status == "succeeded", final.error
    assert final.iterations[0].pose.index == DRAWN


def test_a_given_start_keeps_the_paper_s_protocol(tmp_path, detail):
    stages = StartStages(detail)
    final = run_stored(stored(tmp_path, stages, given=True), stages)
    assert final.iterations[0].pose.index == DRAWN
    assert stages.calls["start pose"] == 0
    assert stages.order[1] == "render"  # the target's detection overlaps the start's render


def test_a_target_without_objects_fails_before_anything_is_rendered(tmp_path, detail):
    stages = StartStages(detail, boxes=0)
    final = run_stored(stored(tmp_path, stages, given=False), stages)
    assert final.status == "failed"
    assert final.error is not None
    assert final.error.type.endswith("no-target-objects")
    assert stages.calls["render"] == 0
    assert stages.calls["start pose"] == 0


@pytest.mark.parametrize("given", [True, False])
def test_an_answer_the_search_finds_ambiguous_is_never_confirmed(tmp_path, detail, given):
    stages = StartStages(detail, ambiguous=True)
    final = run_stored(stored(tmp_path, stages, start=TRUTH, given=given), stages)
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.pose.index == TRUTH
    assert result.ambiguous
    assert not result.confirmed
    assert result.reason.startswith("not confirmed: the answer is ambiguous")


@pytest.mark.parametrize("given", [True, False])
def test_only_a_given_start_is_rendered_before_the_search_is_stored(tmp_path, detail, given):
    """A given start's view is rendered while the submission is checked and stored; a search
    without one records that it was not given, and renders nothing before its target is seen."""
    import asyncio

    import cv2
    import numpy as np

    from services.common.contracts.search import SearchOptions, ViewSettings
    from services.controller.settings import ControllerSettings
    from services.controller.submit import create_search

    class SubmitStages:
        view_settings = ViewSettings()

        def __init__(self) -> None:
            self.early: list[GridIndex] = []

        async def scene(self, scene_id: str, request_id: str = ""):
            return detail

        def render_early(self, scene_id, index, request_id, view_settings=None) -> None:
            self.early.append(index)

        def forget_early(self, request_id: str) -> None:
            pass

    ok, png = cv2.imencode(".png", np.zeros((240, 320, 3), np.uint8))
    assert ok
    stages = SubmitStages()
    start = {"start_theta_deg": 45.0, "start_phi_deg": 90.0} if given else {}
    options = SearchOptions(scene="demo", seed=3, **start)
    store = open_store(f"sqlite:///{tmp_path}/c.sqlite3")
    settings = ControllerSettings(controller_database_url=f"sqlite:///{tmp_path}/c.sqlite3")
    search = asyncio.run(
        create_search(store, stages, png.tobytes(), options, settings, start_early=True)  # type: ignore[arg-type]
    )
    assert search.start_given is given
    assert stages.early == ([search.start.index] if given else [])
    recorded = store.get(search.id)
    assert recorded is not None
    assert recorded.start_given is given
