"""When a dense fit is taken (:func:`services.optimizer.refine_pose.dense_report`): converged
fits that move the pose a little, or further when the image vouches for it; never a fit lost in
clutter, nor one that slipped far."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.contracts.free import FreePose, IntrinsicsUsed
from services.common.geometry.free_camera import FreeCamera, quaternion_of_rotation
from services.optimizer.free import DenseFit, Intrinsics
from services.optimizer.refine_pose import dense_report

START = FreeCamera(position=(0.0, -10.0, 5.0), look_at=(0.0, 0.0, 0.0))
DEPTH = 10.0  # the points' median depth: near bounds 1 unit and 5°


def start_pose() -> FreePose:
    return FreePose(
        position=START.position,
        quaternion_wxyz=quaternion_of_rotation(START.rotation()),
        yaw_pitch_roll_deg=(0.0, 0.0, 0.0),
        intrinsics=IntrinsicsUsed(
            fx_px=400.0, fy_px=400.0, cx_px=160.0, cy_px=120.0, fov_deg=43.6, source="given"
        ),
        correspondences=(),
        residual_px=0.5,
        confidence=0.9,
        position_sigma=None,
        rotation_sigma_deg=None,
    )


def fit(shift: float, turn_deg: float, inliers: int, start_inliers: int, points=1000) -> DenseFit:
    """A fit of the start camera moved ``shift`` along x and turned ``turn_deg`` about z."""
    start = START.rotation().T  # world to camera
    a = math.radians(turn_deg)
    about_z = np.array(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]]
    )
    rotation = start @ about_z.T
    position = np.asarray(START.position) + [shift, 0.0, 0.0]
    return DenseFit(
        rotation=rotation,
        translation=-rotation @ position,
        intrinsics=Intrinsics(400.0, 400.0, 160.0, 120.0),
        residual_px=0.5,
        points=points,
        inliers=inliers,
        start_inliers=start_inliers,
    )


@pytest.mark.parametrize(
    ("shift", "turn", "inliers", "start", "accepted", "said"),
    [
        (0.5, 2.0, 900, 880, True, "refined by the render's edges"),
        (0.5, 2.0, 870, 880, True, "refined"),  # about as many as at the start: noise
        (3.0, 9.0, 900, 400, True, "refined"),  # far, and the image vouches for it
        (3.0, 9.0, 900, 800, False, "implausibly far"),  # far, barely better explained
        (5.0, 9.0, 900, 400, False, "implausibly far"),  # beyond 4 times the near bounds
        (0.5, 25.0, 900, 400, False, "implausibly far"),
        (0.5, 2.0, 400, 300, False, "did not converge"),  # most edges unexplained
        (0.5, 2.0, 800, 880, False, "did not converge"),  # worse than the start
    ],
)
def test_a_fit_is_taken_when_it_converged_and_moved_plausibly(
    shift, turn, inliers, start, accepted, said
):
    report = dense_report(fit(shift, turn, inliers, start), start_pose(), DEPTH, 1.0)
    assert report.accepted is accepted, report.reason
    assert said in report.reason
    assert report.moved == pytest.approx(shift)
    assert report.moved_rotation_deg == pytest.approx(turn)
