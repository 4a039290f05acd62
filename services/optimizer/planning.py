"""Requests to domain problems and plans to answers: what the optimizer's routes call.

Checks everything a request can get wrong that its schema cannot say, naming the field: a scene
that does not exist, a camera or grid missing or disagreeing with the named scene, a grid larger
than the service allows, boxes outside their image, an image whose aspect ratio is not the
camera's, visited poses that are not poses of the grid, a history holding more detections than
the service maps per request, a strategy that needs paper coefficients this camera has none of,
a label that is none of the request's object classes.

With the general detector's shape classes, a second box of another class on one object is
dropped before planning (:func:`~.observations.merge_duplicates`) and the answer's reason says
so.
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np

from services.common.catalog import SceneCatalog
from services.common.contracts.detect import Detection
from services.common.contracts.optimize import (
    CandidatePose,
    GridPose,
    ImageDetections,
    MappedObject,
    MapRequest,
    MapResponse,
    NextPoseRequest,
    NextPoseResponse,
    PoseEstimate,
    StrategyName,
    ViewMatch,
    VisitedView,
)
from services.common.errors import UnprocessableError
from services.common.geometry.grid import GridError, HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import CalibrationStore
from services.optimizer.image_cache import ImageCache, SeenImage
from services.optimizer.mapping import map_exact, map_paper
from services.optimizer.matching import ViewComparison, compare_views
from services.optimizer.observations import Observation, merge_duplicates
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit
from services.optimizer.proxies import ProxyKind, kind_of
from services.optimizer.start_pose import GridViewCache
from services.optimizer.strategies import STRATEGIES, CalibrationMissingError, loose_tolerance
from services.optimizer.view_cache import ViewMappings

__all__ = ["STUCK_VISITS", "OptimizerContext", "check_box", "map_detections", "next_pose"]

STUCK_VISITS: Final = 3
"""A proposed pose already visited this often means the strategy is going round in circles."""

_BOX_SLACK: Final = 1e-6


@dataclass(frozen=True)
class OptimizerContext:
    """What planning needs besides the request: stored coefficients, scenes, limits, and the
    caches that let a search's later requests process and map only their new view (each
    request resends them all): ``images`` keeps what planning makes of each image
    (:mod:`.image_cache`), ``mappings`` each view's exact mapping (:mod:`.view_cache`)."""

    calibrations: CalibrationStore
    catalog: SceneCatalog | None
    default_strategy: StrategyName = "reprojection"
    max_grid_poses: int = 25_000
    max_history_detections: int = 4_000
    mappings: ViewMappings = field(default_factory=ViewMappings, compare=False, repr=False)
    images: ImageCache = field(default_factory=ImageCache, compare=False, repr=False)
    grid_views: GridViewCache = field(default_factory=GridViewCache, compare=False, repr=False)


def _invalid(detail: str, field: str, slug: str = "invalid-request") -> UnprocessableError:
    return UnprocessableError(detail, field=field, slug=slug)


def _setup(
    request: NextPoseRequest, context: OptimizerContext
) -> tuple[CameraSpec, HemisphereGrid]:
    camera, spec = request.camera, request.grid
    if request.scene is not None:
        if context.catalog is None:
            raise _invalid("this optimizer has no scene catalog; give camera and grid", "scene")
        scene = context.catalog.get(request.scene)  # NotFoundError (404) names the field
        if camera is not None and camera != scene.spec.camera:
            raise _invalid(f"camera does not match scene {request.scene!r}", "camera")
        if spec is not None and spec.grid() != scene.spec.search.grid():
            raise _invalid(f"grid does not match scene {request.scene!r}", "grid")
        camera = scene.spec.camera
        grid = scene.spec.search.grid()
    else:
        if camera is None:
            raise _invalid("give the camera (or a scene whose camera to use)", "camera")
        if spec is None:
            raise _invalid("give the grid (or a scene whose grid to use)", "grid")
        grid = spec.grid()
    if grid.size > context.max_grid_poses:
        raise _invalid(
            f"the grid has {grid.size} poses; this service scores at most "
            f"{context.max_grid_poses} (use a larger angle_step_deg)",
            "grid",
            "grid-too-large",
        )
    return camera, grid


def _check_image(image: ImageDetections, camera: CameraSpec, where: str) -> None:
    width, height = image.image_size
    # The image may be scaled, but not reshaped: allow one pixel of rounding.
    if abs(height - width * camera.height / camera.width) > 1.0:
        raise _invalid(
            f"a {width}x{height} image does not have the camera's aspect ratio "
            f"{camera.width}x{camera.height}",
            f"{where}.image_size",
            "inconsistent-image",
        )
    for i, detection in enumerate(image.detections):
        check_box(detection, width, height, f"{where}.detections[{i}].box")


def check_box(detection: Detection, width: int, height: int, field: str) -> None:
    """422 ``box-outside-image`` naming ``field`` unless the box lies inside the image."""
    x1, y1, x2, y2 = detection.box
    inside = (
        -_BOX_SLACK <= x1 < x2 <= width + _BOX_SLACK
        and -_BOX_SLACK <= y1 < y2 <= height + _BOX_SLACK
    )
    if not inside:
        raise _invalid(
            f"box {list(detection.box)} is not a box inside the {width}x{height} image "
            "(need 0 <= x1 < x2 <= width and 0 <= y1 < y2 <= height)",
            field,
            "box-outside-image",
        )


Classes = Mapping[str, ProxyKind] | None


def _classes(request: NextPoseRequest) -> Classes:
    """Identity mode's proxy kind per object class, from the class's shape (not its label)."""
    if request.object_classes is None:
        return None
    return {c.label: kind_of(c.shape) for c in request.object_classes}


def _observe(
    image: ImageDetections, camera: CameraSpec, classes: Classes, where: str
) -> Observation:
    """The image's detections in camera pixels; in identity mode every label must be a class."""
    if classes is not None:
        for i, detection in enumerate(image.detections):
            if detection.label not in classes:
                raise _invalid(
                    f"label {detection.label!r} is none of the object_classes",
                    f"{where}.detections[{i}].label",
                    "unknown-label",
                )
    return Observation.from_detections(image.detections, image.image_size, camera, classes)


def _deduplicated(observation: Observation) -> tuple[Observation, tuple[str, ...]]:
    """Shape-class observations without second boxes on one object, and a note per box gone."""
    if observation.identity:
        return observation, ()  # one class per object: overlapping classes are distinct objects
    return merge_duplicates(observation)


def _seen_target(
    image: ImageDetections, camera: CameraSpec, classes: Classes, where: str
) -> SeenImage:
    """The target checked, in camera pixels and deduplicated (raises naming ``where``'s field)."""
    _check_image(image, camera, where)
    return SeenImage(*_deduplicated(_observe(image, camera, classes, where)))


def _seen_view(
    view: VisitedView, camera: CameraSpec, grid: HemisphereGrid, classes: Classes, where: str
) -> SeenImage:
    """A visited view checked, found on the grid, in camera pixels and deduplicated (raises
    naming ``where``'s field)."""
    _check_image(view, camera, where)
    index = view.pose.as_index()
    if index is not None:
        try:
            grid.validate(index)
        except GridError as exc:
            part = "lat" if index.lat >= grid.ring_count else "lon"
            raise _invalid(str(exc), f"{where}.pose.{part}", "pose-outside-grid") from exc
    else:
        pose = view.pose.as_pose()
        if pose is None:  # PoseQuery validation makes this unreachable
            raise _invalid("no pose given", f"{where}.pose")
        try:
            index = grid.index_of(pose)
        except GridError as exc:
            raise _invalid(
                f"{exc}; visited poses must be grid poses", f"{where}.pose", "pose-outside-grid"
            ) from exc
    flat = grid.flat(index)
    observation, merged = _deduplicated(_observe(view, camera, classes, where))
    return SeenImage(
        observation, merged, flat, float(grid.theta_deg[flat]), float(grid.phi_deg[flat])
    )


def _visits(
    request: NextPoseRequest,
    camera: CameraSpec,
    grid: HemisphereGrid,
    limit: int,
    images: ImageCache,
    setting: str,
    classes: Classes = None,
    notes: list[str] | None = None,
) -> tuple[Visit, ...]:
    total = sum(len(view.detections) for view in request.history)
    if total > limit:
        raise _invalid(
            f"the history holds {total} detections; this service maps at most {limit} per request",
            "history",
            "history-too-large",
        )
    seen = [
        images.get(
            setting,
            view,
            functools.partial(_seen_view, view, camera, grid, classes, f"history[{k}]"),
        )
        for k, view in enumerate(request.history)
    ]
    if seen and notes is not None:  # earlier views' merges were told in earlier answers
        notes.extend(f"current view: {note}" for note in seen[-1].merged)
    return tuple(s.visit for s in seen)


def _grid_pose(grid: HemisphereGrid, flat: int) -> GridPose:
    return GridPose(
        index=grid.unflat(flat),
        theta_deg=float(grid.theta_deg[flat]),
        phi_deg=float(grid.phi_deg[flat]),
    )


def _estimate(grid: HemisphereGrid, estimate: Estimate | None) -> PoseEstimate | None:
    if estimate is None or not math.isfinite(estimate.theta_deg + estimate.phi_deg):
        return None
    residual = estimate.residual_px
    return PoseEstimate(
        grid=_grid_pose(grid, estimate.flat),
        theta_deg=float(np.clip(estimate.theta_deg, 0.0, 90.0)),
        phi_deg=estimate.phi_deg % 360.0,
        residual_px=residual if residual is not None and math.isfinite(residual) else None,
        confidence=estimate.confidence,
    )


def _match(comparison: ViewComparison | None, tolerance_px: float) -> ViewMatch | None:
    """The match of the current view, scored against the loose done test's tolerance: a view
    at its bound scores ``e^{-1/2}`` ≈ 0.61 of its paired share of confidence."""
    if comparison is None:
        return None
    loose = loose_tolerance(comparison, tolerance_px)
    rms = comparison.rms_px if math.isfinite(comparison.rms_px) else None
    return ViewMatch(
        rms_px=rms,
        noise_px=comparison.noise_px,
        pairs=len(comparison.pairs),
        unpaired_current=max(comparison.unpaired_a, 0.0),
        unpaired_target=max(comparison.unpaired_b, 0.0),
        score=float(np.clip(comparison.score(loose), 0.0, 1.0)),
    )


def _answer(
    strategy: StrategyName,
    grid: HemisphereGrid,
    plan: Plan,
    visits: Sequence[Visit],
    match: ViewMatch | None = None,
    notes: Sequence[str] = (),
) -> NextPoseResponse:
    counts = Counter(v.flat for v in visits)
    stuck = not plan.done and counts[plan.next_flat] >= STUCK_VISITS
    reason = plan.reason
    if notes:
        reason += "; one object, two boxes: " + "; ".join(notes)
    if stuck:
        reason += (
            f"; stuck: the proposed pose was visited {counts[plan.next_flat]} times already, "
            "the search is going round in circles"
        )
    return NextPoseResponse(
        strategy=strategy,
        done=plan.done,
        stuck=stuck,
        next=_grid_pose(grid, plan.next_flat),
        move=plan.move,
        estimate=_estimate(grid, plan.estimate),
        ambiguous=plan.ambiguous,
        alternatives=tuple(
            CandidatePose(pose=_grid_pose(grid, flat), score=score)
            for flat, score in plan.alternatives
            if math.isfinite(score)
        ),
        reason=reason,
        match=match,
    )


def next_pose(request: NextPoseRequest, context: OptimizerContext) -> NextPoseResponse:
    """Validate ``request``, plan one step with its strategy and answer.

    Raises
    ------
    NotFoundError
        The named scene does not exist.
    UnprocessableError
        Anything the request gets wrong beyond its schema (module docstring), naming the field.
    """
    strategy: StrategyName = request.strategy or context.default_strategy
    camera, grid = _setup(request, context)
    classes = _classes(request)
    images = context.images
    setting = images.setting(camera, grid, classes)
    seen = images.get(
        setting,
        request.target,
        functools.partial(_seen_target, request.target, camera, classes, "target"),
    )
    target = seen.observation
    notes = [f"target: {note}" for note in seen.merged]
    visits = _visits(
        request, camera, grid, context.max_history_detections, images, setting, classes, notes
    )
    problem = SearchProblem(
        grid=grid,
        camera=camera,
        target=target,
        history=visits,
        tolerance_px=request.tolerances.match_rms_px,
        max_unmatched=request.tolerances.max_unmatched,
        ambiguity_ratio=request.tolerances.ambiguity_ratio,
        calibration=context.calibrations.find(camera),
        mappings=context.mappings,
    )
    try:
        plan = STRATEGIES[strategy].plan(problem)
    except CalibrationMissingError as exc:
        raise _invalid(str(exc), "camera", "no-paper-calibration") from exc
    # The strategies compared these views too; one more small assignment keeps Plan lean.
    comparison = compare_views(visits[-1].observation, target) if visits else None
    match = _match(comparison, problem.tolerance_px)
    return _answer(strategy, grid, plan, visits, match, notes)


def _maybe(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def map_detections(request: MapRequest, calibrations: CalibrationStore) -> MapResponse:
    """Map one view's detections to the ground with the requested method."""
    camera, pose = request.camera, request.pose
    _check_image(request.view, camera, "view")
    observation = Observation.from_detections(
        request.view.detections, request.view.image_size, camera
    )
    if request.method == "paper":
        calibration = calibrations.find(camera)
        if calibration is None:
            raise _invalid(
                "no paper-mapping coefficients are stored for this camera configuration",
                "camera",
                "no-paper-calibration",
            )
        mapped = map_paper(observation.boxes, camera, pose.theta_deg, pose.phi_deg, calibration)
    else:
        mapped = map_exact(
            observation.boxes, observation.kinds, camera, pose.theta_deg, pose.phi_deg
        )
    objects = []
    for i, label in enumerate(observation.labels):
        position = mapped.position[i]
        offset = mapped.offsets[i]
        finite = bool(np.isfinite(position).all())
        objects.append(
            MappedObject(
                label=label,
                position=(float(position[0]), float(position[1])) if finite else None,
                offset=(float(offset[0]), float(offset[1])) if finite else None,
                radius=_maybe(mapped.radius[i]),
                height=_maybe(mapped.height[i]),
                sigma=_maybe(mapped.sigma[i]),
                reliable=bool(mapped.reliable[i]),
            )
        )
    return MapResponse(method=request.method, pose=pose, objects=tuple(objects))
