"""The stages a free search runs over, faked (``FakeStages``: which candidate's render shows the
target's boxes, which fits are accepted), and a search stored and run over them, for the free
loop's tests."""

from __future__ import annotations

import asyncio
from typing import Any

import cv2
import numpy as np

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.free import (
    DenseReport,
    FreeCorrespondence,
    FreePose,
    FreePoseRequest,
    FreePoseResponse,
    IntrinsicsUsed,
    LensBend,
    nearest_grid_pose,
)
from services.common.contracts.refine import (
    FocalCheck,
    RefinePoseRequest,
    RefinePoseResponse,
    TargetRequest,
    TargetResponse,
)
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import (
    Search,
    ViewSettings,
)
from services.common.depth_archive import DepthImage
from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.controller.events import Notifier
from services.controller.runner import SearchRunner
from services.controller.store import SearchStore, open_store, utcnow
from tests.controller.scripted_calls import ScriptedCalls

PNG = b"\x89PNG\r\n\x1a\n" + b"target"
MODEL = ModelInfo(name="demo", classes=("red",), input_size=(640, 640), sha256="d", scene="demo")
BOXES = ((20.0, 30.0, 60.0, 70.0), (100.0, 40.0, 150.0, 90.0), (200.0, 120.0, 260.0, 180.0))
LABELS = ("red", "green", "blue")


def dense_report(**fields: Any) -> DenseReport:
    """A dense fit's report: accepted, 850 of 900 edge points on the target's (600 at the
    start), the pose moved 0.1 and turned 0.1°, the focal length kept; ``fields`` change it."""
    report = DenseReport(
        converged=True,
        accepted=True,
        reason="refined",
        edge_points=900,
        inliers=850,
        start_inliers=600,
        residual_px=0.4,
        focal_fitted=False,
        moved=0.1,
        moved_rotation_deg=0.1,
    )
    return report.model_copy(update=fields)


def candidate(x: float, source: str = "given", pitch: float = 90.0) -> FreePose:
    """A pose at (x, -4, 5) that pairs the three target boxes (its ``pitch`` said, not used)."""
    return FreePose(
        position=(x, -4.0, 5.0),
        quaternion_wxyz=(1.0, 0.0, 0.0, 0.0),
        yaw_pitch_roll_deg=(0.0, pitch, 0.0),
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


class FakeStages(ScriptedCalls):
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
        super().__init__(faults)
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
        self.pitch = 90.0  # the candidates' pitch, as the optimizer says it
        self.focal_check: float | None = None  # the check's focal length off the stated one
        self.lens: LensBend | None = None  # what the fits' lens check says
        self.lens_pose = True  # whether a check that bends offers its lens's pose
        self.prepared: list[tuple[TargetRequest, int]] = []  # and the refinements made by then

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

    async def prepare_target(self, request, target, request_id="") -> TargetResponse:
        """Records the request and how many refinements were made before it."""
        self._call("target")
        self.prepared.append((request, self.calls["refine"]))
        assert target == PNG
        return TargetResponse(film=request.film, levels=3 if request.fit_focal else 1, kept=True)

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
            lens=self.lens,
        )
        check = None
        if request.check_focal and self.focal_check is not None:
            f = k.fx_px * (1.0 + self.focal_check)
            checked = k.model_copy(update={"fx_px": f, "fy_px": f, "source": "estimated"})
            moved = (end + 0.5, y + 0.1, z)
            check = FocalCheck(
                pose=pose.model_copy(update={"position": moved, "intrinsics": checked}),
                fit=fit.model_copy(update={"focal_fitted": True, "focal_sigma": 0.002}),
            )
        bent = None
        if self.lens is not None and self.lens.bends and self.lens_pose:  # 0.3 higher
            lens = LensDistortion(k1=self.lens.k1)
            estimated = k.model_copy(update={"distortion": lens, "source": "estimated"})
            bent = refined.model_copy(
                update={"position": (end, y + 0.1, z + 0.3), "intrinsics": estimated}
            )
        return RefinePoseResponse(pose=refined, fit=fit, focal_check=check, lens_pose=bent)

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
        poses = [candidate(float(x), self.source, self.pitch) for x in range(self.count)]
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


class FirstFitLeads(FakeStages):
    """As :class:`FakeStages`, but the first dense fit moved too far to be accepted: a ``lead``
    when ``lead`` (the image vouches for where it ended), else merely rejected."""

    def __init__(self, scene: SceneDetail, *, lead: bool, **kwargs: Any):
        super().__init__(scene, **kwargs)
        self.lead = lead

    async def refine_pose(self, request, target, render, request_id="") -> RefinePoseResponse:
        out = await super().refine_pose(request, target, render, request_id)
        if len(self.refinements) != 1:
            return out
        said = "the dense fit moved the pose implausibly far"
        fit = out.fit.model_copy(update={"accepted": False, "lead": self.lead, "reason": said})
        return out.model_copy(update={"fit": fit})
