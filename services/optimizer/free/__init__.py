"""A camera anywhere from the target's boxes alone: hypotheses, refinement and an honest status.

:func:`scene_objects` turns a scene file into point sets, :func:`solve_free_pose` answers a
:class:`FreePoseAnswer` from the target's detections (:mod:`.solve` for the steps and the status).
"""

from services.optimizer.free.answer import (
    Correspondence,
    FreePoseAnswer,
    IntrinsicsUsed,
    PoseCandidate,
    Status,
)
from services.optimizer.free.objects import SceneObjects, project_boxes, scene_objects
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.solve import solve_free_pose

__all__ = [
    "Correspondence",
    "FreePoseAnswer",
    "Intrinsics",
    "IntrinsicsUsed",
    "PoseCandidate",
    "SceneObjects",
    "Status",
    "project_boxes",
    "scene_objects",
    "solve_free_pose",
]
