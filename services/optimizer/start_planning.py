"""``POST /start-pose`` requests to predictions and back: what the route calls.

Checks what a request can get wrong beyond its schema, naming the field: a scene that does not
exist (404) or whose grid the optimizer cannot search, boxes outside their image, an image whose
aspect ratio is not the scene camera's, a label that is none of the request's object classes.
The scene's objects projected into its grid are kept per scene file version
(:class:`~.start_pose.GridViewCache`, in the :class:`~.planning.OptimizerContext`).
"""

from __future__ import annotations

import operator
from typing import Final

from services.common.contracts.optimize import (
    CandidatePose,
    GridPose,
    UnsupportedGridError,
    searchable_grid,
)
from services.common.contracts.start_pose import StartPoseRequest, StartPoseResponse
from services.common.errors import UnprocessableError
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.optimizer.free.objects import scene_objects
from services.optimizer.planning import OptimizerContext, _seen_target
from services.optimizer.proxies import kind_of
from services.optimizer.start_pose import StartPrediction, predict_start

__all__ = ["start_pose"]

_CAMERA_FIELDS: Final = operator.attrgetter(*CameraSpec.model_fields)


def _grid_pose(grid: HemisphereGrid, flat: int) -> GridPose:
    return GridPose(
        index=grid.unflat(flat),
        theta_deg=float(grid.theta_deg[flat]),
        phi_deg=float(grid.phi_deg[flat]),
    )


def _response(grid: HemisphereGrid, prediction: StartPrediction) -> StartPoseResponse:
    flat = prediction.flat
    return StartPoseResponse(
        status=prediction.status,
        pose=None if flat is None else _grid_pose(grid, flat),
        score=prediction.score,
        rms_px=prediction.rms_px,
        pairs=prediction.pairs,
        alternatives=tuple(
            CandidatePose(pose=_grid_pose(grid, f), score=s) for f, s in prediction.alternatives
        ),
        reason=prediction.reason,
    )


def start_pose(request: StartPoseRequest, context: OptimizerContext) -> StartPoseResponse:
    """The grid pose of ``request.scene`` whose view the target's detections predict
    (:func:`~.start_pose.predict_start`).

    Raises
    ------
    NotFoundError
        The named scene does not exist.
    UnprocessableError
        Anything the request gets wrong beyond its schema (module docstring), naming the field.
    """
    if context.catalog is None:
        raise UnprocessableError("this optimizer has no scene catalog", field="scene")
    scene = context.catalog.get(request.scene)  # NotFoundError (404) names the field
    camera = scene.spec.camera
    try:
        grid = searchable_grid(scene.spec.search).grid()
    except UnsupportedGridError as exc:
        raise UnprocessableError(
            f"scene {request.scene!r}'s grid cannot be searched: {exc}",
            field="scene",
            slug="unsupported-grid",
        ) from exc
    if grid.size > context.max_grid_poses:
        raise UnprocessableError(
            f"scene {request.scene!r}'s grid has {grid.size} poses; this service scores at "
            f"most {context.max_grid_poses}",
            field="scene",
            slug="grid-too-large",
        )
    classes = (
        None
        if request.object_classes is None
        else {c.label: kind_of(c.shape) for c in request.object_classes}
    )
    target = _seen_target(request.target, camera, classes, "target").observation
    key = ("start-pose", request.scene, scene.version, grid, _CAMERA_FIELDS(camera))
    views = context.grid_views.get(
        key, lambda: scene_objects(scene.spec, scene.assets), grid, camera
    )
    return _response(grid, predict_start(views, grid, target))
