"""Messages of the optimizer's ``POST /start-pose``: the grid pose a hemisphere search should
render first, predicted from the target's detections alone.

The optimizer projects the named scene's objects into every pose of its grid and scores the
target's boxes against each (``services/optimizer/start_pose.py``); a search with no given start
takes its first view there. Kept apart from :mod:`.optimize` (the next-pose step): a caller of
one does not need the other.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import ConfigDict, Field, field_validator

from services.common.base import FrozenModel, Integer, Number
from services.common.contracts.optimize import (
    CandidatePose,
    GridPose,
    ObjectClasses,
    TargetImage,
    optional_not_null,
)
from services.common.geometry.scene import SCENE_ID_PATTERN

__all__ = ["StartPoseRequest", "StartPoseResponse", "StartStatus"]

StartStatus = Literal["found", "ambiguous", "failed"]


class StartPoseRequest(FrozenModel):
    """``POST /start-pose``: the target's detections and the scene they were taken of.

    ``object_classes``, when given, says the detections came from the scene's own detector (as
    in ``POST /next-pose``): a label is an object class and pairs only with its objects. Left
    out, labels are the general detector's shape classes.
    """

    model_config = ConfigDict(json_schema_extra=optional_not_null)

    scene: Annotated[str, Field(pattern=SCENE_ID_PATTERN)]
    target: TargetImage
    object_classes: ObjectClasses | None = None

    @field_validator("object_classes", mode="before")
    @classmethod
    def _not_null(cls, value: object) -> object:
        if value is None:
            raise ValueError("leave the field out instead of sending null")
        return value


class StartPoseResponse(FrozenModel):
    """``POST /start-pose``: the grid pose whose predicted view explains the target best.

    ``status`` is ``found`` when that pose is the one to start from; ``ambiguous`` when a pose
    more than 1.5 grid steps away explains the target about as well (``alternatives``: a
    symmetric layout, or too few objects); ``failed`` when no pose explains it (too few of the
    target's detections pair with the scene's objects). ``pose`` is the best pose in any case but
    ``failed`` without a single pair: the likeliest pose the target gives, a better start than a
    random one even when unsure (the search's controller starts there). ``rms_px`` is the RMS
    box-edge difference of its pairs (camera pixels), ``score`` its score (lower is better,
    comparable with the alternatives'), ``pairs`` the target detections paired with an object
    there.
    """

    status: StartStatus
    pose: GridPose | None
    score: Number | None
    rms_px: Annotated[Number, Field(ge=0.0)] | None
    pairs: Annotated[Integer, Field(ge=0)]
    alternatives: tuple[CandidatePose, ...] = ()
    reason: str
