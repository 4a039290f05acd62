"""A camera anywhere from the target's boxes, then refined by one render; an honest status.

:func:`scene_objects` turns a scene file into point sets, :func:`solve_free_pose` answers a
:class:`FreePoseAnswer` from the target's detections (:mod:`.solve` for the steps and the status),
and :func:`refine_dense` refines a pose by one render with depth (:mod:`.dense`).
"""

from services.optimizer.free.answer import (
    Correspondence,
    FreePoseAnswer,
    IntrinsicsUsed,
    PoseCandidate,
    Status,
)
from services.optimizer.free.dense import DenseFit, refine_dense
from services.optimizer.free.objects import SceneObjects, project_boxes, scene_objects
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.solve import solve_free_pose

__all__ = [
    "Correspondence",
    "DenseFit",
    "FreePoseAnswer",
    "Intrinsics",
    "IntrinsicsUsed",
    "PoseCandidate",
    "SceneObjects",
    "Status",
    "project_boxes",
    "refine_dense",
    "scene_objects",
    "solve_free_pose",
]
