"""The search loop with fake stages (no HTTP): an any-time answer when no view is confirmed,
failures kept for real errors, and object classes sent only for the scene's own model."""

from __future__ import annotations

import asyncio

import pytest

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.optimize import (
    GridPose,
    NextPoseRequest,
    NextPoseResponse,
    ViewMatch,
)
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex
from services.controller.events import Notifier
from services.controller.runner import SearchRunner
from services.controller.store import SearchStore, utcnow

PNG = b"\x89PNG\r\n\x1a\n" + b"target"
GENERAL = ModelInfo(name="general", classes=("sphere",), input_size=(640, 640), sha256="g")
OWN = ModelInfo(name="demo", classes=("red",), input_size=(640, 640), sha256="d", scene="demo")


class FakeStages:
    """Renders a pose's lat/lon as bytes; the optimizer never says done and scores lon 2 best."""

    def __init__(self, scene: SceneDetail, *, models=(GENERAL, GENERAL), stuck_after=99, boxes=1):
        self.detail = scene
        self.grid = scene_grid_of(scene)
        self.target_model, self.view_model = models
        self.stuck_after = stuck_after
        self.boxes = boxes
        self.requests: list[NextPoseRequest] = []

    async def scene(self, scene_id: str, request_id: str = "") -> SceneDetail:
        return self.detail

    def forget_early(self, request_id: str) -> None:
        pass

    async def render(self, scene_id: str, index: GridIndex, request_id: str = "") -> bytes:
        return f"P6 {index.lat} {index.lon}".encode()

    async def detect(
        self, image: bytes, media_type: str, request_id: str = "", scene: str | None = None
    ) -> DetectResponse:
        model = self.target_model if image == PNG else self.view_model
        label = "red" if model.scene else "sphere"
        detections = tuple(
            Detection(label=label, class_id=0, confidence=0.9, box=(10 + i, 10, 50 + i, 50))
            for i in range(self.boxes)
        )
        return DetectResponse(detections=detections, image_size=(320, 240), model=model)

    async def optimize(self, request: NextPoseRequest, request_id: str = "") -> NextPoseResponse:
        self.requests.append(request)
        here = request.history[-1].pose
        lon = here.lon or 0
        nxt = GridIndex(lat=3, lon=(lon + 1) % 8)
        score = 0.8 if lon == 2 else 0.1 * lon / 8
        return NextPoseResponse(
            strategy="reprojection",
            done=False,
            stuck=len(request.history) >= self.stuck_after,
            next=self.grid_pose(nxt),
            move="E",
            estimate=None,
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


def scene_grid_of(detail: SceneDetail):
    from services.common.geometry.grid import grid_for

    g = detail.grid
    return grid_for(g.angle_step_deg, g.min_theta_deg, g.max_theta_deg)


@pytest.fixture
def detail(catalog) -> SceneDetail:
    scene = catalog.get("demo")
    return SceneDetail(id="demo", spec=scene.spec, grid=scene.spec.search)


def run(tmp_path, stages: FakeStages, max_iterations: int = 6) -> Search:
    store = SearchStore(f"sqlite:///{tmp_path}/c.sqlite3")
    now = utcnow()
    search = Search(
        id="s1",
        status="queued",
        scene="demo",
        strategy="reprojection",
        start=stages.grid_pose(GridIndex(lat=3, lon=0)),
        seed=1,
        max_iterations=max_iterations,
        created_at=now,
        updated_at=now,
        target_size=(320, 240),
    )
    store.create(search, PNG)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]

    async def go() -> None:
        await runner._run("s1")

    asyncio.run(go())
    final = store.get("s1")
    assert final is not None
    return final


def test_a_search_out_of_iterations_answers_its_best_visited_pose(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert not result.confirmed
    assert result.pose.index == GridIndex(lat=3, lon=2)
    assert result.confidence == pytest.approx(0.8)
    assert result.renders == 6
    assert result.reason.startswith("not confirmed: no view matched the target within 6 views")
    assert [it.match.score for it in final.iterations if it.match][2] == pytest.approx(0.8)


def test_a_stuck_search_answers_its_best_visited_pose(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, stuck_after=4), max_iterations=20)
    assert final.status == "succeeded"
    assert final.result is not None
    assert not final.result.confirmed
    assert final.result.pose.index == GridIndex(lat=3, lon=2)
    assert "kept coming back to the same poses" in final.result.reason
    assert len(final.iterations) == 4


def test_a_target_without_objects_still_fails(tmp_path, detail):
    final = run(tmp_path, FakeStages(detail, boxes=0))
    assert final.status == "failed"
    assert final.error is not None
    assert final.error.type.endswith("no-target-objects")


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
