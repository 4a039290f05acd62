"""The free search with fake stages (no HTTP), as tests/controller/test_runner.py tests the
hemisphere one: a found pose confirmed by its render, an ambiguous one never confirmed, the
next alternative rendered when a render disagrees (within the render budget), failures a user
can act on, resumption, the film scaled to the view width; and the free options of a
submission."""

from __future__ import annotations

import asyncio
import math
from collections import Counter

import cv2
import numpy as np
import pytest

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.free import (
    DenseReport,
    FreeCorrespondence,
    FreePose,
    FreePoseRequest,
    FreePoseResponse,
    IntrinsicsUsed,
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.contracts.refine import RefinePoseRequest, RefinePoseResponse
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import (
    Iteration,
    Search,
    SearchOptions,
    StageTimings,
    ViewSettings,
)
from services.common.depth_archive import DepthImage
from services.common.errors import ProblemDetails, UnprocessableError
from services.common.geometry.free_camera import FreeCamera
from services.controller.events import Notifier
from services.controller.form import photo_intrinsics
from services.controller.free_match import compare_view
from services.controller.free_refine import edges_agree, edges_contradict, edges_pin
from services.controller.free_verdict import choice, others_standing
from services.controller.runner import SearchRunner
from services.controller.stages import StageError
from services.controller.store import SearchStore, open_store, utcnow

PNG = b"\x89PNG\r\n\x1a\n" + b"target"
MODEL = ModelInfo(name="demo", classes=("red",), input_size=(640, 640), sha256="d", scene="demo")
BOXES = ((20.0, 30.0, 60.0, 70.0), (100.0, 40.0, 150.0, 90.0), (200.0, 120.0, 260.0, 180.0))
LABELS = ("red", "green", "blue")


def candidate(x: float, source: str = "given") -> FreePose:
    """A pose at (x, -4, 5) that pairs the three target boxes."""
    return FreePose(
        position=(x, -4.0, 5.0),
        quaternion_wxyz=(1.0, 0.0, 0.0, 0.0),
        yaw_pitch_roll_deg=(0.0, 90.0, 0.0),
        intrinsics=IntrinsicsUsed(
            fx_px=386.0, fy_px=386.0, cx_px=160.0, cy_px=120.0, fov_deg=45.0, source=source
        ),
        correspondences=tuple(
            FreeCorrespondence(detection=i, object=label, label=label, residual_px=0.5)
            for i, label in enumerate(LABELS)
        ),
        residual_px=0.5,
        confidence=0.9,
        position_sigma=0.01,
        rotation_sigma_deg=0.05,
    )


class FakeStages:
    """The target shows :data:`BOXES`; the optimizer answers ``status`` with the candidates at
    x = 0, 1, 2, ... (the first is the pose, the rest alternatives); a render at candidate
    ``right`` shows the target's boxes, any other shows them 30 px to the right; the dense fit
    from the render at a candidate in ``edges`` (default: ``right`` only) leaves most of its
    edges on the target's, from any other it does not converge. ``faults`` as in test_runner:
    a call answers ``n`` times, then raises."""

    def __init__(
        self,
        scene: SceneDetail,
        *,
        status: str = "found",
        count: int = 1,
        right: int = 0,
        target_size: tuple[int, int] = (320, 240),
        boxes: tuple[tuple[float, float, float, float], ...] = BOXES,
        faults: dict[str, tuple[int, BaseException]] | None = None,
        refine: str | BaseException = "accepted",
        refits: int = 0,
        edges: tuple[int, ...] | None = None,
        inliers: int = 800,
        ambiguity: str | None = None,
        turn: float = 0.0,
        meet: bool = False,
    ):
        self.detail = scene
        self.status = status
        self.count = count
        self.right = right
        self.target_size = target_size
        self.boxes = boxes
        self.faults = faults or {}
        self.calls: Counter[str] = Counter()
        self.rendered: list[tuple[FreeCamera, tuple[int, int]]] = []
        self.requests: list[FreePoseRequest] = []
        self.refine = refine
        self.refits = refits  # how many first fits ask for a render at the refined pose
        self.refinements: list[RefinePoseRequest] = []
        self.edges = (right,) if edges is None else edges
        self.inliers = inliers  # of 900 edge points, when a fit explains the target
        self.ambiguity = ambiguity  # why the optimizer's answer is ambiguous
        self.turn = turn  # degrees an accepted fit turns the pose
        self.meet = meet  # every fit ends at the right candidate (x = right)
        self.source = "given"  # where the optimizer says its intrinsics came from

    def _call(self, name: str) -> None:
        self.calls[name] += 1
        if name in self.faults:
            answers, error = self.faults[name]
            if self.calls[name] > answers:
                raise error

    async def wait_for_replica(self, stage: str, timeout_s: float) -> bool:
        return False

    async def scene(self, scene_id: str, request_id: str = "") -> SceneDetail:
        self._call("scene")
        return self.detail

    def forget_early(self, request_id: str) -> None:
        pass

    def settings_for(self, view_settings: ViewSettings | None) -> ViewSettings:
        return view_settings or ViewSettings()

    async def render_camera(
        self, scene_id, camera, size, request_id="", view_settings=None, *, with_depth=False
    ):
        """The renderer's archive: its first pixel's red says which candidate was rendered."""
        self._call("render")
        assert with_depth
        self.rendered.append((camera, size))
        rgb = np.zeros((size[1], size[0], 3), np.uint8)
        rgb[0, 0, 0] = round(camera.position[0])
        depth = np.full(rgb.shape[:2], 5.0, np.float32)
        return DepthImage(depth=depth, objects=np.full(depth.shape, -1, np.int16), rgb=rgb).npz()

    async def refine_pose(self, request, target, render, request_id="") -> RefinePoseResponse:
        """Moves the pose 0.1 along y (and fits the focal when asked); answers as ``refine``
        says: ``accepted``, ``rejected`` (converged, moved too far) or a refusal."""
        self._call("refine")
        self.refinements.append(request)
        assert target == PNG
        assert DepthImage.from_npz(render).rgb is not None
        if isinstance(self.refine, BaseException):
            raise self.refine
        pose = request.pose
        k = pose.intrinsics
        if request.fit_focal:
            k = k.model_copy(update={"fx_px": 390.0, "fy_px": 390.0, "source": "estimated"})
        x, y, z = pose.position
        end = float(self.right) if self.meet else x
        refined = pose.model_copy(update={"position": (end, y + 0.1, z), "intrinsics": k})
        explained = round(x) in self.edges
        accepted = explained and self.refine == "accepted"
        fit = DenseReport(
            converged=explained,
            accepted=accepted,
            reason="refined by the render's edges"
            if accepted
            else "the dense fit moved the pose implausibly far"
            if explained
            else "the dense fit did not converge",
            edge_points=900,
            inliers=self.inliers if explained else 300,
            start_inliers=600,
            residual_px=0.4,
            focal_fitted=request.fit_focal,
            moved=0.1,
            moved_rotation_deg=self.turn,
            render_again=len(self.refinements) <= self.refits,
        )
        return RefinePoseResponse(pose=refined, fit=fit)

    async def detect(self, image, media_type, request_id="", scene=None) -> DetectResponse:
        if image == PNG:
            self._call("detect target")
            size, shift, scale = self.target_size, 0.0, 1.0
            boxes = self.boxes
        else:
            self._call("detect view")
            rgb = cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR)
            x = int(rgb[0, 0, 2])  # the first pixel's red (OpenCV decodes to BGR)
            size, scale = (rgb.shape[1], rgb.shape[0]), rgb.shape[1] / self.target_size[0]
            shift = 0.0 if x == self.right else 30.0
            boxes = BOXES
        detections = tuple(
            Detection(
                label=label,
                class_id=i,
                confidence=0.9,
                box=((x1 + shift) * scale, y1 * scale, (x2 + shift) * scale, y2 * scale),
            )
            for i, (label, (x1, y1, x2, y2)) in enumerate(zip(LABELS, boxes, strict=False))
        )
        return DetectResponse(detections=detections, image_size=size, model=MODEL)

    async def free_pose(self, request: FreePoseRequest, request_id: str = "") -> FreePoseResponse:
        self._call("free-pose")
        self.requests.append(request)
        if self.status == "failed":
            return FreePoseResponse(status="failed", reason="failed: no detection names", pose=None)
        poses = [candidate(float(x), self.source) for x in range(self.count)]
        grid = self.detail.spec.search.grid()
        return FreePoseResponse(
            status=self.status,  # type: ignore[arg-type]
            reason=f"{self.status}: the boxes",
            pose=poses[0],
            alternatives=tuple(poses[1:]),
            nearest_grid=nearest_grid_pose(poses[0].position, grid),
            usable_detections=3,
            ambiguity=self.ambiguity,  # type: ignore[arg-type]
        )


def stored(tmp_path, stages: FakeStages, max_iterations: int = 4, **fields) -> SearchStore:
    store = open_store(f"sqlite:///{tmp_path}/c.sqlite3")
    grid = stages.detail.spec.search.grid()
    start = nearest_grid_pose((0.0, 0.0, 1.0), grid)
    now = utcnow()
    search = Search(
        id="s1",
        status="queued",
        scene="demo",
        strategy="reprojection",
        start=start,
        seed=1,
        max_iterations=max_iterations,
        created_at=now,
        updated_at=now,
        target_size=stages.target_size,
        mode="free",
        **fields,
    )
    store.create(search, PNG)
    return store


def run_stored(store: SearchStore, stages: FakeStages) -> Search:
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]
    asyncio.run(runner._run("s1"))
    final = store.get("s1")
    assert final is not None
    return final


def run(tmp_path, stages: FakeStages, max_iterations: int = 4, **fields) -> Search:
    return run_stored(stored(tmp_path, stages, max_iterations, **fields), stages)


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
                            "detect view": 1, "refine": 1}  # fmt: skip
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
    """Three rival candidates, the first one right and pinned by its edges, the intrinsics
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
        assert "its edges pin it: 900 of 900" in result.reason
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


def test_rivals_are_not_rendered_when_the_agreeing_pose_could_not_be_confirmed(tmp_path, detail):
    """0.89 of the render's edges on the target's: its rivals' renders could not confirm it."""
    stages = FakeStages(detail, status="ambiguous", count=3, ambiguity="rivals", inliers=800)
    final = run(tmp_path, stages, intrinsics=PhotoIntrinsics(fov_deg=45.0))
    result = final.result
    assert result is not None
    assert result.renders == 1
    assert not result.confirmed
    (only,) = final.iterations
    assert only.done
    assert only.agrees
    assert "rivals" not in only.reason


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


class RefusesTheSecondFit(FakeStages):
    """As :class:`FakeStages`, but the second dense fit is not accepted (it moved too far)."""

    async def refine_pose(self, request, target, render, request_id="") -> RefinePoseResponse:
        out = await super().refine_pose(request, target, render, request_id)
        if len(self.refinements) != 2:
            return out
        fit = out.fit.model_copy(
            update={"accepted": False, "reason": "the dense fit moved the pose implausibly far"}
        )
        return out.model_copy(update={"fit": fit})


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
    final = run(tmp_path, stages, view_settings=ViewSettings(width=160))
    assert final.result is not None
    assert final.result.confirmed
    camera, size = stages.rendered[0]
    assert size == (160, 120)
    assert camera.fx_px == pytest.approx(386.0 / 4)
    assert camera.cx_px == pytest.approx(40.0)


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


def test_a_free_search_resumed_after_its_agreeing_render_answers_it(tmp_path, detail):
    first = FakeStages(detail)
    store = stored(tmp_path, first)
    run_stored(store, first)
    done = store.get("s1")
    assert done is not None
    assert done.result is not None
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


def test_a_resumed_search_answers_a_followed_candidate_at_the_pose_its_render_checked(
    tmp_path, detail
):
    """Resumed after recording an iteration rendered at its candidate's dense fit: the answer is
    the pose that render was made at (no fit to refine it by), not the candidate's box pose,
    whose own render disagreed."""
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
    assert result.confirmed
    assert result.free.pose.position == pytest.approx((5.0, -3.9, 5.0))
    # the focal length the render was made with: the first fit's (no intrinsics given)
    assert result.free.pose.intrinsics.fx_px == pytest.approx(390.0)
    assert result.free.pose.intrinsics.fov_deg == pytest.approx(
        2 * math.degrees(math.atan(160 / 390))
    )


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
    # a fit at the target's chance says nothing, and one below it contradicts
    assert fit.share(600) == pytest.approx(0.0 if chance else 0.6)
