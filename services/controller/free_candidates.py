"""The candidates a free search renders, as it rendered them: the optimizer's poses, each
replaced by the pose at its dense fit when the render there stood for it
(:func:`~services.controller.free_iterations.worth_following`)."""

from __future__ import annotations

from services.common.contracts.free import FreePose, FreePoseResponse
from services.common.contracts.search import Iteration
from services.common.geometry.camera import fov_deg_of
from services.common.geometry.free_camera import (
    rotation_of_quaternion,
    yaw_pitch_roll_of_rotation,
)

__all__ = ["as_rendered", "with_candidate"]


def with_candidate(answer: FreePoseResponse, k: int, pose: FreePose) -> FreePoseResponse:
    """``answer`` with its ``k``-th candidate (its pose, then its alternatives) ``pose``."""
    if k == 0:
        return answer.model_copy(update={"pose": pose})
    alternatives = list(answer.alternatives)
    alternatives[k - 1] = pose
    return answer.model_copy(update={"alternatives": tuple(alternatives)})


def as_rendered(
    answer: FreePoseResponse, history: list[Iteration], size: tuple[int, int]
) -> FreePoseResponse:
    """``answer`` with each candidate that a recorded iteration shows rendered at its dense fit
    (``candidate_camera``: a resumed search) at the pose that render was made at: its camera's
    position and orientation, its focal length back in the target's pixels (``size``)."""
    candidates = answer.candidates
    for it in history:
        camera = it.camera
        if it.candidate_camera is None or camera is None or camera.quaternion_wxyz is None:
            continue
        if camera.fx_px is None or camera.fy_px is None or it.index >= len(candidates):
            continue
        pose = candidates[it.index]
        scale = it.image_size[0] / size[0]
        fx, fy = camera.fx_px / scale, camera.fy_px / scale
        fov = fov_deg_of(fx, size[0])
        ypr = yaw_pitch_roll_of_rotation(rotation_of_quaternion(camera.quaternion_wxyz))
        rendered = pose.model_copy(
            update={
                "position": camera.position,
                "quaternion_wxyz": camera.quaternion_wxyz,
                "yaw_pitch_roll_deg": ypr,
                "intrinsics": pose.intrinsics.model_copy(
                    update={"fx_px": fx, "fy_px": fy, "fov_deg": fov}
                ),
            }
        )
        answer = with_candidate(answer, it.index, rendered)
    return answer
