"""What a search looks for and what it has seen, and the optimizer's question made from it.

Detector classes: when the target was detected by the scene's own model (``model.scene`` is
the search's scene), its labels are the scene's object classes and the optimizer is told so
(``object_classes``). That holds only while every view of the request came from the very model
(sha256) that detected the target; if a view's model differs (a model swapped mid-search) or
is unknown (a view recorded by an earlier version), the request leaves ``object_classes`` out and
the optimizer treats labels as mere evidence (different labels pair at a cost) rather than
re-detecting the target.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.optimize import (
    GridPose,
    NextPoseRequest,
    NextPoseResponse,
    SearchableGrid,
    TargetImage,
    VisitedView,
)
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import Iteration, Search, StageTimings
from services.common.geometry.pose import Pose, PoseQuery
from services.common.scene_models import ObjectClass, object_classes

__all__ = ["Progress", "View", "at"]


View = DetectResponse | Iteration
"""A view's detections, as they came: the detector's answer for a pose rendered now, or the
iteration that saw a pose before (a pose is rendered once). The view becomes an
:class:`Iteration` (recorded) and a :class:`VisitedView` (the optimizer's request): the two
contracts it travels through, and no other shape."""


def _model_of(view: View) -> str | None:
    """The sha256 of the model that detected ``view`` (None when recorded by an earlier
    version)."""
    return view.model.sha256 if isinstance(view, DetectResponse) else view.detector_sha256


def _classes_for(
    search: Search,
    scene: SceneDetail,
    target_model: ModelInfo | None,
    views: Iterable[View],
) -> tuple[ObjectClass, ...] | None:
    """The scene's object classes when the target and every view came from the scene's own
    model (module docstring), else None."""
    if target_model is None or target_model.scene != search.scene:
        return None
    if any(_model_of(view) != target_model.sha256 for view in views):
        return None
    return object_classes(scene.spec)


def at(pose: GridPose) -> tuple[int, int]:
    """Where ``pose`` is on the grid: (lat, lon)."""
    return (pose.index.lat, pose.index.lon)


def _visited(
    pose: GridPose, image_size: tuple[int, int], detections: tuple[Detection, ...]
) -> VisitedView:
    return VisitedView(
        pose=PoseQuery(lat=pose.index.lat, lon=pose.index.lon),
        image_size=image_size,
        detections=detections,
    )


@dataclass
class Progress:
    """What a search looks for and what it has seen: its iterations, the view at every pose it
    rendered (a pose is rendered once: a view is reused when the search comes back to it), and
    the target's detections, with those the store does not hold yet."""

    search: Search
    scene: SceneDetail
    grid: SearchableGrid
    history: list[Iteration]
    views: dict[tuple[int, int], Iteration]  # the iteration that saw each pose first
    target: tuple[Detection, ...] | None
    target_size: tuple[int, int]
    target_model: ModelInfo | None  # None for a target recorded by an earlier version
    unrecorded_target: DetectResponse | None = None  # recorded with the next iteration

    @classmethod
    def recorded(cls, search: Search, scene: SceneDetail, grid: SearchableGrid) -> Progress:
        """What ``search`` recorded: nothing for a new search, its iterations for a resumed one."""
        history = list(search.iterations)
        views: dict[tuple[int, int], Iteration] = {}
        for it in history:
            views.setdefault(at(it.pose), it)
        return cls(
            search,
            scene,
            grid,
            history,
            views,
            search.target_detections,
            search.target_size,
            search.target_model,
        )

    @property
    def renders(self) -> int:
        return len(self.views)

    @property
    def finished(self) -> bool:
        """Whether the last recorded iteration was done."""
        return bool(self.history) and self.history[-1].done

    @property
    def pose(self) -> GridPose | None:
        """Where the search goes on: the start pose, or the next pose of its last iteration."""
        return self.history[-1].next_pose if self.history else self.search.start

    def saw_target(self, seen: DetectResponse) -> None:
        """Take the target's detections, to be recorded with the next iteration."""
        self.target = seen.detections
        self.target_size = seen.image_size
        self.target_model = seen.model
        self.unrecorded_target = seen

    def take_unrecorded_target(self) -> DetectResponse | None:
        """The target's detections if the store does not hold them yet (then they are its)."""
        seen, self.unrecorded_target = self.unrecorded_target, None
        return seen

    def request(self, target: TargetImage, pose: GridPose, view: View) -> NextPoseRequest:
        """The optimizer's question once it sees ``view`` at ``pose``: the target and every view
        so far, with the scene's object classes when they apply (:func:`_classes_for`)."""
        history = [_visited(it.pose, it.image_size, it.detections) for it in self.history]
        history.append(_visited(pose, view.image_size, view.detections))
        views = [*self.views.values(), view]
        classes = _classes_for(self.search, self.scene, self.target_model, views)
        return NextPoseRequest(
            strategy=self.search.strategy,
            camera=self.scene.spec.camera,
            grid=self.grid,
            target=target,
            history=tuple(history),
            **({} if classes is None else {"object_classes": classes}),
        )

    def add(
        self, pose: GridPose, view: View, answer: NextPoseResponse, timings: StageTimings
    ) -> Iteration:
        """Record, in the history, ``view`` at ``pose`` and the optimizer's ``answer`` to it."""
        estimate = answer.estimate
        iteration = Iteration(
            index=len(self.history),
            pose=pose,
            image_size=view.image_size,
            detections=view.detections,
            detector_sha256=_model_of(view),
            timings=timings,
            estimate=(
                Pose(theta_deg=estimate.theta_deg, phi_deg=estimate.phi_deg)
                if estimate is not None
                else None
            ),
            estimate_grid=estimate.grid if estimate is not None else None,
            confidence=estimate.confidence if estimate is not None else 0.0,
            ambiguous=answer.ambiguous,
            next_pose=answer.next,
            done=answer.done,
            reason=answer.reason,
            match=answer.match,
        )
        self.history.append(iteration)
        self.views.setdefault(at(pose), iteration)
        return iteration
