"""The box-only pose solver (:func:`services.optimizer.free.solve_free_pose`) on a free target,
as a perfect detector would feed it, and the count that must stay at zero: answers ``found``
that are wrong.

The detections are the renderer's visible boxes of the target's usable objects (the ones the
baseline pairs), each edge plus N(0, σ²) with σ = :func:`~.solve.box_sigma_px` (as the box-only
bound), clipped to the film, labelled with the object's identity class as the scene's own
detector names it (:func:`services.common.scene_models.object_classes`, which
:func:`~services.optimizer.free.scene_objects` carries as ``labels``: the solver pairs a
detection only with objects of its label). The target's intrinsics go in only when it gives
them; otherwise the solver estimates the focal length.

An ``ambiguous`` answer's best pose counts in the error table (a search would render it first);
only ``failed`` counts as no pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np

from cosmos.bench.free_targets.draw import FreeTarget
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import PoseError
from cosmos.bench.free_targets.solve import box_sigma_px
from services.common.contracts.detect import Detection
from services.optimizer.free import FreePoseAnswer, Intrinsics, SceneObjects, solve_free_pose

__all__ = [
    "SOLVER",
    "WRONG",
    "WRONG_LOOSE",
    "answer_estimate",
    "confirmed_wrong",
    "solve_target",
    "target_detections",
]

SOLVER: Final = "box solver"
"""The solver's name in the tables."""
WRONG: Final = (0.10, 5.0)
"""(position / r, rotation °) outside which a ``found`` answer is confirmed wrong."""
WRONG_LOOSE: Final = (0.05, 2.0)
"""The tighter count of ``found`` answers that miss."""


def target_detections(
    target: FreeTarget, objects: SceneObjects, rng: np.random.Generator
) -> list[Detection]:
    """The target's usable objects' visible boxes with edge noise, as labelled detections."""
    camera = target.annotations.camera
    sigma = box_sigma_px(camera.width)
    limits = np.array([camera.width, camera.height] * 2, dtype=np.float64)
    class_ids = {label: i for i, label in enumerate(dict.fromkeys(objects.labels))}
    detections = []
    for obj in target.annotations.objects:
        if obj.name not in target.usable or obj.box is None:
            continue
        box = np.clip(np.asarray(obj.box) + rng.normal(0.0, sigma, 4), 0.0, limits)
        if box[2] <= box[0] or box[3] <= box[1]:
            continue
        label = objects.labels[objects.names.index(obj.name)]
        detections.append(
            Detection(
                label=label,
                class_id=class_ids[label],
                confidence=0.9,
                box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
            )
        )
    return detections


def solve_target(
    target: FreeTarget, objects: SceneObjects, rng: np.random.Generator
) -> FreePoseAnswer:
    """:func:`solve_free_pose` on :func:`target_detections`, with the true intrinsics only when
    the target gives them."""
    camera = target.annotations.camera
    intrinsics = (
        Intrinsics(camera.fx, camera.fy, camera.cx, camera.cy) if target.intrinsics_given else None
    )
    detections = target_detections(target, objects, rng)
    return solve_free_pose(objects, detections, camera.width, camera.height, intrinsics)


def answer_estimate(answer: FreePoseAnswer) -> Estimate | None:
    """The answer's best pose as an :class:`Estimate` (None when it has none: ``failed``)."""
    pose = answer.pose
    if pose is None:
        return None
    return Estimate(
        pose.rotation(), np.asarray(pose.position, dtype=np.float64), pose.intrinsics.fov_deg
    )


def confirmed_wrong(
    errors: Sequence[PoseError], statuses: Sequence[str | None], limit: tuple[float, float] = WRONG
) -> int:
    """How many answers are ``found`` while their pose lies outside ``limit`` (position as a
    fraction of r, rotation in degrees)."""
    return sum(
        status == "found" and not error.within(*limit)
        for error, status in zip(errors, statuses, strict=True)
    )
