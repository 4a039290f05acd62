"""The search loop with fake stages (no HTTP): a confirmed answer, an any-time answer when no view
is confirmed, a failure a user can act on for every real error (and no replica address in it),
resumption from what was recorded, and object classes sent only for the scene's own model."""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import re
import time

import pytest
from pydantic import ValidationError

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.free import DenseReport
from services.common.contracts.optimize import (
    GridPose,
    NextPoseRequest,
    NextPoseResponse,
    PoseEstimate,
    ViewMatch,
)
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import (
    TERMINAL_STATUSES,
    Iteration,
    Search,
    StageTimings,
    ViewSettings,
)
from services.common.errors import ProblemDetails
from services.common.geometry.pose import GridIndex, Pose
from services.controller.broker import BrokerError
from services.controller.events import Notifier
from services.controller.grid_edges import grid_free_pose
from services.controller.runner import NotRetryable, SearchRunner, StillStopping
from services.controller.stages import StageError
from services.controller.store import SearchStore, open_store, utcnow
from tests.controller.scripted_calls import ScriptedCalls

PNG = b"\x89PNG\r\n\x1a\n" + b"target"
GENERAL = ModelInfo(name="general", classes=("sphere",), input_size=(640, 640), sha256="g")
OWN = ModelInfo(name="demo", classes=("red",), input_size=(640, 640), sha256="d", scene="demo")


class FakeStages(ScriptedCalls):
    """Renders a pose's lat/lon as bytes; the optimizer scores lon 2 best and says done only
    after ``done_after`` views.

    ``faults`` scripts failures: a call (``scene``, ``render``, ``detect target``, ``detect view``,
    ``optimize``) answers ``n`` times, then raises the error. ``calls`` counts every call.

    A stage no replica serves comes back, its faults gone, at the ``back_after``-th wait for it
    (:meth:`wait_for_replica`); until then (or always, for None) a wait times out. ``waits``
    records each wait: the stage and its timeout.
    """

    def __init__(
        self,
        scene: SceneDetail,
        *,
        models=(GENERAL, GENERAL),
        stuck_after=99,
        done_after=99,
        boxes=1,
        faults: dict[str, tuple[int, BaseException]] | None = None,
        back_after: int | None = None,
        settled_at: GridIndex | None = None,
        estimate_theta: float = 0.5,
        ring: int = 3,
    ):
        self.detail = scene
        self.settled_at = settled_at
        self.ring = ring
        self.estimate_theta = estimate_theta
        self.grid = scene.grid.grid()
        self.target_model, self.view_model = models
        self.stuck_after = stuck_after
        self.done_after = done_after
        self.boxes = boxes
        super().__init__(faults)
        self.back_after = back_after
        self.waits: list[tuple[str, float]] = []
        self.requests: list[NextPoseRequest] = []
        self.rendered_with: list[ViewSettings | None] = []

    async def wait_for_replica(self, stage: str, timeout_s: float) -> bool:
        self.waits.append((stage, timeout_s))
        await asyncio.sleep(0)
        if self.back_after is None or len(self.waits) < self.back_after:
            return False
        self.faults.clear()
        return True

    async def scene(self, scene_id: str, request_id: str = "") -> SceneDetail:
        self._call("scene")
        return self.detail

    def forget_early(self, request_id: str) -> None:
        pass

    async def render(
        self,
        scene_id: str,
        index: GridIndex,
        request_id: str = "",
        view_settings: ViewSettings | None = None,
    ) -> bytes:
        self._call("render")
        self.rendered_with.append(view_settings)
        return f"P6 {index.lat} {index.lon}".encode()

    def settings_for(self, view_settings: ViewSettings | None) -> ViewSettings:
        return view_settings or ViewSettings()

    async def render_camera(self, scene_id, camera, size, request_id="", view_settings=None, **_):
        self._call("render depth")
        return b"archive"

    async def refine_pose(self, request, target, render, request_id="") -> RefinePoseResponse:
        """A fit that pins the camera on the hemisphere at :attr:`settled_at` (its grid pose,
        nudged 0.4° in θ), or one the optimizer did not accept (None)."""
        self._call("refine")
        pinned = self.settled_at is not None
        pose = request.pose
        if self.settled_at is not None:
            at = self.grid.pose(self.settled_at)
            moved = Pose(theta_deg=at.theta_deg + 0.4, phi_deg=at.phi_deg)
            radius = self.detail.spec.camera.radius
            pose = grid_free_pose(moved, radius, self.detail.spec.camera.fov_deg, (320, 240))
        fit = DenseReport(
            converged=pinned,
            accepted=pinned,
            reason="refined" if pinned else "the dense fit did not converge",
            edge_points=900,
            inliers=880 if pinned else 200,
            start_inliers=600,
            residual_px=0.4,
            focal_fitted=False,
            moved=0.1,
            moved_rotation_deg=2.0,
        )
        return RefinePoseResponse(pose=pose, fit=fit)

    async def detect(
        self, image: bytes, media_type: str, request_id: str = "", scene: str | None = None
    ) -> DetectResponse:
        self._call("detect target" if image == PNG else "detect view")
        model = self.target_model if image == PNG else self.view_model
        label = "red" if model.scene else "sphere"
        detections = tuple(
            Detection(label=label, class_id=0, confidence=0.9, box=(10 + i, 10, 50 + i, 50))
            for i in range(self.boxes)
        )
        return DetectResponse(detections=detections, image_size=(320, 240), model=model)

    async def optimize(self, request: NextPoseRequest, request_id: str = "") -> NextPoseResponse:
        self._call("optimize")
        self.requests.append(request)
        here = request.history[-1].pose
        lon = here.lon or 0
        nxt = GridIndex(lat=self.ring, lon=(lon + 1) % 8)
        score = 0.8 if lon == 2 else 0.1 * lon / 8
        done = len(request.history) >= self.done_after
        grid_pose = self.grid_pose(GridIndex(lat=here.lat or 0, lon=lon))
        return NextPoseResponse(
            strategy="reprojection",
            done=done,
            stuck=len(request.history) >= self.stuck_after,
            next=grid_pose if done else self.grid_pose(nxt),
            move="stay" if done else "E",
            estimate=PoseEstimate(
                grid=grid_pose,
                theta_deg=grid_pose.theta_deg + self.estimate_theta,
                phi_deg=grid_pose.phi_deg,
                residual_px=1.0,
                confidence=0.9,
            )
            if done
            else None,
            ambiguous=False,
            alternatives=(),
            reason="the views differ",
            match=ViewMatch(
                rms_px=3.0,
                noise_px=1.0,
                pairs=1,
                unpaired_current=0,
                unpaired_target=0,
                score=score,
            ),  # fmt: skip
        )

    def grid_pose(self, index: GridIndex) -> GridPose:
        flat = self.grid.flat(index)
        return GridPose(
            index=index,
            theta_deg=float(self.grid.theta_deg[flat]),
            phi_deg=float(self.grid.phi_deg[flat]),
        )


_BACK_END = {"url": ""}
"""The database :func:`stored` opens in this module's tests (empty: a SQLite file)."""
_OPENED: list[SearchStore] = []


@pytest.fixture(autouse=True, params=["sqlite", "postgresql"])
def _back_end(request):
    """Every runner test on both back ends: :func:`stored` opens a fresh database of each."""
    if request.param == "postgresql":
        _BACK_END["url"] = request.getfixturevalue("postgres").new_schema()
    yield
    _BACK_END["url"] = ""
    while _OPENED:
        _OPENED.pop().close()


def stored(
    tmp_path,
    stages: FakeStages,
    max_iterations: int = 6,
    view_settings=None,
    strategy: str = "reprojection",
) -> SearchStore:
    """A store holding search ``s1`` as submitted: queued, its target image, nothing else."""
    store = open_store(_BACK_END["url"] or f"sqlite:///{tmp_path}/c.sqlite3")
    _OPENED.append(store)
    now = utcnow()
    search = Search(
        id="s1",
        status="queued",
        scene="demo",
        strategy=strategy,
        start=stages.grid_pose(GridIndex(lat=3, lon=0)),
        seed=1,
        max_iterations=max_iterations,
        created_at=now,
        updated_at=now,
        target_size=(320, 240),
        view_settings=view_settings,
    )
    store.create(search, PNG)
    return store


def run_stored(store: SearchStore, stages: FakeStages, outage_budget_s: float = 60.0) -> Search:
    """Run search ``s1`` of ``store`` on a fresh runner (as a restarted controller would)."""
    runner = SearchRunner(
        store,
        stages,  # type: ignore[arg-type]
        Notifier(),
        max_concurrent=1,
        outage_budget_s=outage_budget_s,
    )

    async def go() -> None:
        await runner._run("s1")

    asyncio.run(go())
    final = store.get("s1")
    assert final is not None
    return final


def run(
    tmp_path, stages: FakeStages, max_iterations: int = 6, outage_budget_s: float = 60.0
) -> Search:
    return run_stored(stored(tmp_path, stages, max_iterations), stages, outage_budget_s)


def test_a_search_out_of_iterations_answers_its_best_visited_pose(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail))
    assert final.status == "succeeded", final.error
    assert final.error is None
    result = final.result
    assert result is not None
    assert not result.confirmed
    assert result.pose.index == GridIndex(lat=3, lon=2)
    assert result.confidence == pytest.approx(0.8)
    assert result.renders == 7  # and the render with depth for the edges
    assert result.reason.startswith("not confirmed: no view matched the target within 6 views")
    assert "the render's edges did not settle it (the dense fit did not converge)" in result.reason
    assert [it.match.score for it in final.iterations if it.match][2] == pytest.approx(0.8)


def test_an_unconfirmed_answer_moves_where_the_render_s_edges_pin_the_camera(tmp_path, detail):
    """The best visited pose is lat 3 lon 2; the dense fit from its render pins the camera
    0.4° from lat 3 lon 3, on the hemisphere: that is the answer, still unconfirmed."""
    stages = FakeStages(detail, settled_at=GridIndex(lat=3, lon=3))
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert not result.confirmed
    assert result.pose.index == GridIndex(lat=3, lon=3)
    on_grid = stages.grid.pose(GridIndex(lat=3, lon=3))
    assert result.refined_pose.theta_deg == pytest.approx(on_grid.theta_deg + 0.4, abs=1e-6)
    assert result.refined_pose.phi_deg == pytest.approx(on_grid.phi_deg, abs=1e-6)
    assert "nearest lat 3 lon 3, not lat 3 lon 2 (not rendered there)" in result.reason
    assert result.renders == 7
    assert stages.calls["render depth"] == stages.calls["refine"] == 1
    assert result.refit_timings is not None


def test_the_paper_s_strategies_are_not_settled(tmp_path, detail):
    stages = FakeStages(detail, settled_at=GridIndex(lat=3, lon=3))
    paper = run_stored(stored(tmp_path, stages, strategy="paper"), stages)
    assert paper.result is not None
    assert paper.result.pose.index == GridIndex(lat=3, lon=2)
    assert paper.result.renders == 6
    assert stages.calls["render depth"] == 0


def test_a_confirmed_answer_is_not_settled(tmp_path, detail):
    stages = FakeStages(detail, done_after=2, settled_at=GridIndex(lat=3, lon=3))
    done = run(tmp_path, stages)
    assert done.result is not None
    assert done.result.confirmed
    assert stages.calls["render depth"] == stages.calls["refine"] == 0


def test_a_confirmed_answer_near_a_boundary_is_checked_by_the_edges(tmp_path, detail):
    """Done at lat 3 lon 2 (θ 30°) on an estimate at θ 33.5°, 0.25° short of the boundary with
    lat 4: the render's edges pin the camera 0.4° from lat 4 lon 2, and the answer moves there,
    no longer confirmed."""
    stages = FakeStages(
        detail, done_after=3, estimate_theta=3.5, settled_at=GridIndex(lat=4, lon=2)
    )
    final = run(tmp_path, stages)
    result = final.result
    assert result is not None
    assert result.pose.index == GridIndex(lat=4, lon=2)
    assert not result.confirmed
    assert result.reason.startswith("not confirmed: the render's edges put the camera at")
    assert "the views had confirmed it: the views differ" in result.reason
    assert result.renders == 4
    assert stages.calls["render depth"] == 1


@pytest.mark.parametrize(
    ("ring", "estimate_theta"),
    [(3, 3.5), (1, 0.5)],
    ids=["near a boundary", "looking 75 degrees down"],
)
def test_a_confirmed_answer_the_edges_keep_stays_confirmed(tmp_path, detail, ring, estimate_theta):
    """Checked by the render's edges near a boundary (θ 33.5° on lat 3, θ 30°) or looking
    steeply down (θ 15.5° on lat 1, θ 15°), the answer they pin to its grid pose stays
    confirmed."""
    stages = FakeStages(
        detail,
        done_after=3,
        ring=ring,
        estimate_theta=estimate_theta,
        settled_at=GridIndex(lat=ring, lon=2),
    )
    result = run(tmp_path, stages).result
    assert result is not None
    assert result.pose.index == GridIndex(lat=ring, lon=2)
    assert result.confirmed
    assert result.reason.endswith("nearest this grid pose")
    assert result.renders == 4
    assert stages.calls["render depth"] == stages.calls["refine"] == 1


def test_a_steep_confirmed_answer_the_edges_cannot_check_is_not_confirmed(tmp_path, detail):
    refused = StageError("renderer", ProblemDetails(title="Bad request", status=422))
    stages = FakeStages(
        detail,
        done_after=3,
        ring=1,
        settled_at=GridIndex(lat=1, lon=2),
        faults={"render depth": (0, refused)},
    )
    result = run(tmp_path, stages).result
    assert result is not None
    assert result.pose.index == GridIndex(lat=1, lon=2)
    assert not result.confirmed
    assert result.reason.startswith("not confirmed: looking 74° down, the views hardly tell")
    assert "(no render:" in result.reason
    assert result.reason.endswith("the views had confirmed it: the views differ")


def test_a_render_for_the_edges_that_fails_keeps_the_answer(tmp_path, detail):
    refused = StageError("renderer", ProblemDetails(title="Bad request", status=422))
    stages = FakeStages(
        detail, settled_at=GridIndex(lat=3, lon=3), faults={"render depth": (0, refused)}
    )
    final = run(tmp_path, stages)
    assert final.status == "succeeded"
    result = final.result
    assert result is not None
    assert result.pose.index == GridIndex(lat=3, lon=2)
    assert result.renders == 6
    assert "the render's edges did not settle it (no render:" in result.reason
    assert stages.calls["refine"] == 0


def test_a_stuck_search_answers_its_best_visited_pose(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, stuck_after=4), max_iterations=20)
    assert final.status == "succeeded"
    assert final.error is None
    assert final.result is not None
    assert not final.result.confirmed
    assert final.result.pose.index == GridIndex(lat=3, lon=2)
    assert "kept coming back to the same poses" in final.result.reason
    assert len(final.iterations) == 4


def test_the_scene_s_own_model_sends_its_object_classes(tmp_path, detail):
    stages = FakeStages(detail, models=(OWN, OWN))
    run(tmp_path, stages, max_iterations=2)
    classes = stages.requests[0].object_classes
    assert classes is not None
    assert [c.label for c in classes][0] == "red"


def test_the_models_are_recorded_so_a_resumed_search_keeps_its_classes(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, models=(OWN, OWN)), max_iterations=2)
    assert final.target_model == OWN
    assert [it.detector_sha256 for it in final.iterations] == ["d", "d"]


@pytest.mark.parametrize("models", [(GENERAL, GENERAL), (OWN, GENERAL)])
def test_general_or_mixed_models_send_no_object_classes(tmp_path, detail, models):
    stages = FakeStages(detail, models=models)
    run(tmp_path, stages, max_iterations=2)
    assert all(r.object_classes is None for r in stages.requests)


# -- the confirmed answer and resumption ---------------------------------------------------------


def test_a_search_the_optimizer_calls_done_answers_its_estimate(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, done_after=3))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.confirmed
    assert result.pose.index == GridIndex(lat=3, lon=2)
    assert result.refined_pose.theta_deg == pytest.approx(result.pose.theta_deg + 0.5)
    assert result.confidence == pytest.approx(0.9)
    assert result.renders == 3
    assert [it.done for it in final.iterations] == [False, False, True]
    assert final.target_detections is not None
    assert final.target_model == GENERAL


def test_an_interrupted_search_resumes_from_its_recorded_iterations(tmp_path, detail):
    first = FakeStages(detail, faults={"render": (2, asyncio.CancelledError())})
    store = stored(tmp_path, first, max_iterations=4)
    with pytest.raises(asyncio.CancelledError):
        run_stored(store, first)
    interrupted = store.get("s1")
    assert interrupted is not None
    assert interrupted.status == "running"
    assert [it.index for it in interrupted.iterations] == [0, 1]

    again = FakeStages(detail)
    final = run_stored(store, again)
    assert final.status == "succeeded", final.error
    views = {"scene": 1, "render": 2, "detect view": 2, "optimize": 2}
    assert again.calls == {**views, "render depth": 1, "refine": 1}  # its answer unconfirmed
    assert [len(r.history) for r in again.requests] == [3, 4]
    assert final.result is not None
    assert final.result.pose.index == GridIndex(lat=3, lon=2)
    assert final.result.renders == 5  # 4 views and the render with depth for the edges


def test_a_resumed_search_renders_with_the_view_settings_it_was_submitted_with(tmp_path, detail):
    """Its own settings go with every render, before and after the interruption (the stages
    render with them, not with the controller's current ones: tests/web/test_routes.py)."""
    own = ViewSettings(spp=2, width=160)
    first = FakeStages(detail, faults={"render": (2, asyncio.CancelledError())})
    store = stored(tmp_path, first, max_iterations=4, view_settings=own)
    with pytest.raises(asyncio.CancelledError):
        run_stored(store, first)
    again = FakeStages(detail)
    final = run_stored(store, again)
    assert final.status == "succeeded", final.error
    assert final.view_settings == own
    assert first.rendered_with == [own, own]
    assert again.rendered_with == [own, own]


def recorded(stages: FakeStages, lon: int, **fields) -> Iteration:
    """An iteration at lat 3, ``lon`` as an earlier controller recorded it."""
    box = Detection(label="sphere", class_id=0, confidence=0.9, box=(10, 10, 50, 50))
    return Iteration(
        index=0,
        pose=stages.grid_pose(GridIndex(lat=3, lon=lon)),
        image_size=(320, 240),
        detections=(box,),
        timings=StageTimings(render_ms=1.0, detect_ms=1.0, optimize_ms=1.0, total_ms=3.0),
        **fields,
    )


def test_a_pose_seen_before_is_not_rendered_again(tmp_path, detail):
    stages = FakeStages(detail)  # goes east round ring 3 (8 poses) and on
    final = run(tmp_path, stages, max_iterations=11)
    assert final.status == "succeeded", final.error
    assert len(final.iterations) == 11
    assert stages.calls["render"] == stages.calls["detect view"] == 8
    assert final.result is not None
    assert final.result.renders == 9  # 8 poses and the render with depth for the edges
    assert [it.timings.render_ms for it in final.iterations[8:]] == [0.0] * 3


def test_a_search_resumed_without_its_target_detects_the_target_once(tmp_path, detail):
    stages = FakeStages(detail)
    store = stored(tmp_path, stages, max_iterations=3)
    # it goes on at the pose it saw: the target is detected before, not with, a new render
    first = recorded(stages, 0, next_pose=stages.grid_pose(GridIndex(lat=3, lon=0)))
    store.add_iteration("s1", first, status="running")
    final = run_stored(store, stages)
    assert final.status == "succeeded", final.error
    assert stages.calls["detect target"] == 1
    assert stages.calls["render"] == 1
    assert final.target_detections is not None
    assert len(final.target_detections) == 1
    assert final.target_model == GENERAL


def test_a_search_resumed_after_its_last_view_was_done_answers_it(tmp_path, detail):
    stages = FakeStages(detail)
    store = stored(tmp_path, stages)
    pose = stages.grid_pose(GridIndex(lat=3, lon=0))
    last = recorded(stages, 0, done=True, confidence=0.7, estimate_grid=pose)
    store.add_iteration("s1", last, status="running")
    final = run_stored(store, stages)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    assert final.result.confirmed
    assert final.result.pose == pose
    assert final.result.renders == 1
    assert stages.calls == {"scene": 1}


# -- failures: what a user reads --------------------------------------------------------------

REPLICAS = ("http://10.0.0.7:8001", "http://10.0.0.8:8001")
ADDRESS = re.compile(r"https?://|\b\d{1,3}(\.\d{1,3}){3}\b|localhost|:\d{2,5}\b")


def assert_failed(final: Search, slug: str, status: int, title: str, *words: str) -> None:
    """``final`` failed with problem ``slug``, its ``title``, a detail saying ``words`` and
    naming no replica or other address."""
    assert final.status == "failed"
    assert final.result is None
    error = final.error
    assert error is not None
    assert error.type == f"urn:cosmos:problem:{slug}"
    assert error.status == status
    assert error.title == title
    assert error.detail is not None
    for word in words:
        assert word in error.detail
    assert not ADDRESS.search(error.detail), error.detail


def unavailable(stage: str, kind: str) -> BrokerError:
    """What the broker raises when every attempt failed (its reasons name the replicas)."""
    host, port = REPLICAS[1].removeprefix("http://").split(":")
    return BrokerError(
        stage,
        kind,
        [
            f"{REPLICAS[0]}: HTTP 503",
            f"{REPLICAS[1]}: ConnectionRefusedError: [Errno 111] "
            f"Connect call failed ('{host}', {port})",
            f"{REPLICAS[0]}: timed out (60 s)",
        ],
    )


# (call, answers before it fails, stage, the broker's task kind, the stage's refusal)
STAGE_CALLS = [
    ("scene", 0, "renderer", "scene", "scene 'demo' is not in this renderer's catalog"),
    ("render", 1, "renderer", "render", "pose lat 3 lon 1 is not on scene demo's grid"),
    ("detect target", 0, "detector", "detect", "the image is not a PNG, JPEG or binary PPM"),
    ("detect view", 1, "detector", "detect", "the image has 90000000 pixels, over 40000000"),
    ("optimize", 1, "optimizer", "optimize", "history.1.pose: lat 9 is not on the grid"),
]


@pytest.mark.parametrize(("call", "answers", "stage", "kind", "why"), STAGE_CALLS)
def test_a_stage_that_refuses_fails_the_search_with_its_reason(
    tmp_path, detail, call, answers, stage, kind, why
):
    problem = ProblemDetails(
        type="urn:cosmos:problem:bad-request", title="Bad request", status=422, detail=why
    )
    stages = FakeStages(detail, faults={call: (answers, StageError(stage, problem))})
    final = run(tmp_path, stages)
    assert_failed(final, "stage-refused", 422, f"{stage.capitalize()} refused", stage, why)
    assert len(final.iterations) == answers  # what was done before is kept


@pytest.mark.parametrize(("call", "answers", "stage", "kind", "why"), STAGE_CALLS)
def test_a_stage_nobody_serves_fails_the_search_naming_the_stage_not_its_replicas(
    tmp_path, detail, caplog, call, answers, stage, kind, why
):
    """The stage stays away longer than the search waits: the error says what happened and how
    to resume the search."""
    stages = FakeStages(detail, faults={call: (answers, unavailable(stage, kind))})
    final = run(tmp_path, stages, outage_budget_s=60.0)
    assert_failed(
        final,
        "stage-unavailable",
        503,
        f"No {stage} available",
        f"the {stage} was unavailable",
        "did not come back within 60 s",
        "POST /searches/s1/retry",
    )
    assert len(final.iterations) == answers
    assert [stage for stage, _ in stages.waits] == [stage]
    assert 59.0 < stages.waits[0][1] <= 60.0
    assert REPLICAS[1] in caplog.text  # the operator still learns which replicas failed


@pytest.mark.parametrize(("call", "answers", "stage", "kind", "why"), STAGE_CALLS)
def test_a_stage_that_comes_back_within_the_budget_is_called_again(
    tmp_path, detail, call, answers, stage, kind, why
):
    stages = FakeStages(
        detail, faults={call: (answers, unavailable(stage, kind))}, back_after=1, done_after=3
    )
    final = run(tmp_path, stages)
    assert final.status == "succeeded", final.error
    assert [stage for stage, _ in stages.waits] == [stage]
    assert final.result is not None
    assert final.result.renders == 3
    assert stages.calls["render"] == 3 + (call == "render")  # only the failed call is repeated


def test_a_search_without_an_outage_budget_fails_at_once(tmp_path, detail):
    gone = BrokerError("optimizer", "optimize", [f"{REPLICAS[0]}: HTTP 502"])
    stages = FakeStages(detail, faults={"optimize": (0, gone)}, back_after=1)
    final = run(tmp_path, stages, outage_budget_s=0.0)
    assert_failed(
        final, "stage-unavailable", 503, "No optimizer available", "did not come back within 0 s"
    )
    assert stages.waits == []


class BackButBroken(FakeStages):
    """The stage answers /health again at once, yet every task still fails (a replica that is
    up but broken): the search keeps trying only until its outage budget is spent."""

    async def wait_for_replica(self, stage: str, timeout_s: float) -> bool:
        self.waits.append((stage, timeout_s))
        await asyncio.sleep(0.01)
        return True


def test_a_stage_that_answers_health_but_fails_every_task_fails_the_search_in_time(
    tmp_path, detail
):
    gone = unavailable("detector", "detect")
    stages = BackButBroken(detail, faults={"detect view": (0, gone)})
    started = time.monotonic()
    final = run(tmp_path, stages, outage_budget_s=0.2)
    assert time.monotonic() - started < 2.0
    assert_failed(final, "stage-unavailable", 503, "No detector available", "within 0.2 s")
    assert 5 <= len(stages.waits) <= 25
    assert [timeout for _, timeout in stages.waits] == sorted(
        (timeout for _, timeout in stages.waits), reverse=True
    )


def test_a_stage_without_replicas_fails_the_search_saying_so(tmp_path, detail):
    stages = FakeStages(detail, faults={"render": (0, BrokerError("renderer", "render", []))})
    final = run(tmp_path, stages)
    assert_failed(
        final, "stage-unavailable", 503, "No renderer available", "no renderer replica is known"
    )


def test_an_optimizer_answer_the_controller_cannot_read_fails_the_search(tmp_path, detail):
    answer = FakeStages(detail).grid_pose(GridIndex(lat=3, lon=1)).model_dump()
    newer = (  # an optimizer of another version: ``next`` renamed
        '{"strategy": "reprojection", "done": false, "stuck": false, "move": "E",'
        ' "estimate": null, "ambiguous": false, "alternatives": [], "reason": "",'
        f' "next_pose": {json.dumps(answer)}}}'
    )
    try:
        NextPoseResponse.model_validate_json(newer)
    except ValidationError as exc:
        malformed = exc
    stages = FakeStages(detail, faults={"optimize": (1, malformed)})
    final = run(tmp_path, stages)
    assert_failed(
        final, "bad-optimizer-answer", 502, "Bad optimizer answer", "next: ", "next_pose", "version"
    )
    assert final.error is not None
    assert {"field": "next", "message": "Field required"} in (final.error.errors or [])
    assert len(final.iterations) == 1


def test_a_scene_grid_the_optimizer_cannot_search_fails_the_search(tmp_path, detail):
    search = detail.spec.search.model_copy(update={"angle_step_deg": 0.5})
    fine = detail.model_copy(update={"spec": detail.spec.model_copy(update={"search": search})})
    stages = FakeStages(fine)
    final = run(tmp_path, stages)
    assert_failed(
        final, "unsupported-grid", 422, "Grid not supported", "demo", "search.angle_step_deg"
    )
    assert stages.calls == {"scene": 1}


def test_a_target_without_objects_fails_the_search(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, boxes=0))
    assert_failed(
        final,
        "no-target-objects",
        422,
        "Nothing to search for",
        "no objects in the target image",
    )
    assert final.target_detections == ()
    assert final.iterations == ()


def test_a_bug_fails_the_search_with_an_internal_error_and_logs_it(tmp_path, detail, caplog):
    bug = RuntimeError(f"lost the connection to {REPLICAS[0]}")
    final = run(tmp_path, FakeStages(detail, faults={"optimize": (2, bug)}))
    assert_failed(final, "internal-error", 500, "Internal error", "unexpectedly", "logged")
    assert len(final.iterations) == 2
    crash = next(r for r in caplog.records if r.name == "cosmos.controller" and r.exc_info)
    assert crash.exc_info is not None
    assert crash.exc_info[1] is bug


class SlowRender(FakeStages):
    """Renders take a moment: the target's detection, started beside the render, ends first."""

    async def render(
        self,
        scene_id: str,
        index: GridIndex,
        request_id: str = "",
        view_settings: ViewSettings | None = None,
    ) -> bytes:
        await asyncio.sleep(0.02)
        return await super().render(scene_id, index, request_id, view_settings)


def test_a_target_detection_that_fails_while_the_render_fails_too_is_not_left_unretrieved(
    tmp_path, detail, caplog
):
    """The target's detection fails first, the render then fails as well: the search fails with
    the render's error, and asyncio has no "Task exception was never retrieved" to log."""
    refused = ProblemDetails(title="Bad request", status=422, detail="not an image")
    stages = SlowRender(
        detail,
        faults={
            "detect target": (0, StageError("detector", refused)),
            "render": (0, StageError("renderer", refused)),
        },
    )
    with caplog.at_level(logging.ERROR, logger="asyncio"):
        final = run(tmp_path, stages)
        gc.collect()  # an unretrieved exception is logged when its task is collected
    assert_failed(final, "stage-refused", 422, "Renderer refused", "not an image")
    assert stages.calls["detect target"] == 1
    assert "never retrieved" not in caplog.text


# -- retrying a search an outage failed ---------------------------------------------------------


def test_a_search_an_outage_failed_resumes_where_it_stopped_when_retried(tmp_path, detail):
    stages = FakeStages(
        detail, faults={"detect view": (2, unavailable("detector", "detect"))}, done_after=4
    )
    store = stored(tmp_path, stages)
    failed = run_stored(store, stages)
    assert_failed(failed, "stage-unavailable", 503, "No detector available")
    assert len(failed.iterations) == 2

    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]
    queued = runner.retry("s1")
    assert queued.status == "queued"
    assert queued.error is None
    assert runner.queued == 1
    stages.faults.clear()  # the detector is back
    stages.calls.clear()
    final = run_stored(store, stages)
    assert final.status == "succeeded", final.error
    assert final.error is None
    assert [it.index for it in final.iterations] == [0, 1, 2, 3]
    assert stages.calls == {"scene": 1, "render": 2, "detect view": 2, "optimize": 2}


def test_only_a_search_an_outage_failed_is_retried(tmp_path, detail):
    refused = StageError("detector", ProblemDetails(title="Bad request", status=422))
    stages = FakeStages(detail, faults={"detect view": (0, refused)})
    store = stored(tmp_path, stages)
    run_stored(store, stages)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]
    with pytest.raises(NotRetryable, match="a reason a retry does not change"):
        runner.retry("s1")
    store.update("s1", status="succeeded")
    with pytest.raises(NotRetryable, match="s1 is succeeded"):
        runner.retry("s1")
    with pytest.raises(KeyError):
        runner.retry("nope")
    assert runner.queued == 0


async def closed_at_once(runner: SearchRunner) -> None:
    """Close ``runner``; fail if that takes seconds or leaves a task behind."""
    closing = asyncio.create_task(runner.close())
    await asyncio.wait({closing}, timeout=5.0)
    if not closing.done():
        closing.cancel()
        pytest.fail("close() did not return")
    closing.result()
    assert asyncio.all_tasks() == {asyncio.current_task()}  # no worker, no search left


def test_close_returns_at_once_right_after_a_search_ends(tmp_path, detail):
    """close() as a search ends, before its worker has resumed: the worker's cancellation is
    the worker's, not the search's. (The worker took it for the search's and waited for the
    next search, so close() waited for ever; and close() swallowed its own cancellation, so a
    timeout around it returned as if it had closed.)"""
    stages = FakeStages(detail, done_after=2)
    store = stored(tmp_path, stages)
    notifier = Notifier()
    runner = SearchRunner(store, stages, notifier, max_concurrent=2)  # type: ignore[arg-type]

    async def go() -> None:
        await runner.start()  # resumes s1, left queued
        with notifier.following("s1"):
            while True:
                changed = notifier.current("s1")
                search = store.get("s1")
                assert search is not None
                if search.status in TERMINAL_STATUSES:
                    break
                await changed.wait()
        assert runner.running == 1  # the search has ended; its worker has not resumed yet
        await closed_at_once(runner)

    asyncio.run(go())
    final = store.get("s1")
    assert final is not None
    assert final.status == "succeeded", final.error
    assert runner.running == 0


def test_close_stops_a_running_search_which_resumes_later(tmp_path, detail):
    """close() while a search waits for a stage: the worker and the search stop, and the
    search stays 'running' for the next start to resume."""
    stages = FakeStages(detail, done_after=3)
    store = stored(tmp_path, stages)
    rendering = asyncio.Event()
    render = stages.render

    async def slow_render(
        scene_id: str, index: GridIndex, request_id: str = "", view_settings=None
    ) -> bytes:
        rendering.set()
        await asyncio.sleep(60)
        return await render(scene_id, index, request_id, view_settings)

    stages.render = slow_render  # type: ignore[method-assign]
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]

    async def go() -> None:
        await runner.start()
        await rendering.wait()
        await closed_at_once(runner)

    asyncio.run(go())
    stopped = store.get("s1")
    assert stopped is not None
    assert stopped.status == "running"
    stages.render = render  # type: ignore[method-assign]
    assert run_stored(store, stages).status == "succeeded"


def stubborn_renders(stages: FakeStages) -> tuple[asyncio.Event, asyncio.Event]:
    """Make ``stages`` render for ever, and take its time to stop once cancelled: set the
    first event when a render starts; a cancelled render stops when the second one is set."""
    rendering, release = asyncio.Event(), asyncio.Event()

    async def stubborn_render(*args, **kwargs) -> bytes:
        rendering.set()
        try:
            await asyncio.sleep(60)
        finally:
            await release.wait()
        raise AssertionError("unreachable")

    stages.render = stubborn_render  # type: ignore[method-assign]
    return rendering, release


def test_close_cancelled_is_cancelled(tmp_path, detail):
    """close() cancelled while a search winds down (here: a render that takes its time to
    stop) stops waiting, and a later close() finishes the job."""
    stages = FakeStages(detail, done_after=3)
    store = stored(tmp_path, stages)
    rendering, release = stubborn_renders(stages)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]

    async def go() -> None:
        await runner.start()
        await rendering.wait()
        closing = asyncio.create_task(runner.close())
        await asyncio.sleep(0.05)
        assert not closing.done()  # the search is still winding down
        closing.cancel()
        await asyncio.wait({closing}, timeout=5.0)
        assert closing.cancelled()
        release.set()
        await closed_at_once(runner)

    asyncio.run(go())
    stopped = store.get("s1")
    assert stopped is not None
    assert stopped.status == "running"


# -- cancelling ---------------------------------------------------------------------------------


@pytest.mark.parametrize("call", ["scene", "render", "detect view", "optimize"])
def test_a_cancel_is_never_lost_whenever_it_arrives(tmp_path, detail, call):
    """A search cancelled while it waits for ``call`` ends cancelled, stays so in the store, and
    a restarted controller does not resume it. (Cancelled while it waited for its scene, before
    its first write, its run's last write set it 'running' again: no worker ran it, and the next
    start ran it to its end.)"""
    stages = FakeStages(detail, done_after=3)
    store = stored(tmp_path, stages)
    waiting, release = asyncio.Event(), asyncio.Event()
    original = getattr(stages, call.split()[0])

    async def held(*args, **kwargs):
        if call != "detect view" or args[0] != PNG:
            waiting.set()
            await release.wait()
        return await original(*args, **kwargs)

    setattr(stages, call.split()[0], held)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]

    async def go() -> None:
        await runner.start()  # takes s1, left queued
        await waiting.wait()
        assert runner.cancel("s1").status == "cancelled"
        release.set()
        for _ in range(100):
            if runner.running == 0:
                break
            await asyncio.sleep(0.01)
        assert runner.running == 0
        assert runner.stopping == 0  # the cancel is forgotten once its run stopped
        await closed_at_once(runner)

    asyncio.run(go())
    final = store.get("s1")
    assert final is not None
    assert final.status == "cancelled"
    assert store.unfinished() == []  # a restart does not resume it


def test_a_cancelled_search_is_deleted_only_once_its_run_has_stopped(tmp_path, detail):
    """Its run writes what it did as it stops: deleting it before would lose those writes (or
    fail them); afterwards it goes with its image and iterations."""
    stages = FakeStages(detail, done_after=3)
    store = stored(tmp_path, stages)
    rendering, release = stubborn_renders(stages)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]

    async def go() -> None:
        await runner.start()
        await rendering.wait()
        runner.cancel("s1")
        await asyncio.sleep(0.01)
        with pytest.raises(StillStopping):
            runner.delete("s1")
        release.set()
        while runner.running:
            await asyncio.sleep(0.01)
        deleted = runner.delete("s1")
        assert deleted is not None
        assert deleted[0] is None  # no owner: stored without keys
        assert runner.delete("s1") is None
        await closed_at_once(runner)

    asyncio.run(go())
    assert store.get("s1") is None
    assert not store.holds_image("s1")
