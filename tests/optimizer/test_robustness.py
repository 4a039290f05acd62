"""Arbitrary valid-looking requests never crash planning or mapping (no 5xx): random boxes,
labels, colours, poses and histories on the full π/24 grid, warnings treated as errors."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.common.contracts.detect import Detection
from services.common.contracts.optimize import (
    ImageDetections,
    MapRequest,
    NextPoseRequest,
    TargetImage,
    VisitedView,
)
from services.common.errors import ServiceError
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import Pose, PoseQuery
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import CalibrationStore
from services.optimizer.planning import OptimizerContext, map_detections, next_pose

CAMERA = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)
GRID = GridSpec(angle_step_deg=7.5, min_theta_deg=0.0, max_theta_deg=90.0)
CONTEXT = OptimizerContext(calibrations=CalibrationStore.load(), catalog=None)
LABELS = ["sphere", "cube", "cylinder", "cone", "mesh", "teapot"]


@st.composite
def detections(draw, max_size: int = 6) -> tuple[Detection, ...]:
    out = []
    for _ in range(draw(st.integers(0, max_size))):
        x1 = draw(st.floats(0.0, 318.0))
        y1 = draw(st.floats(0.0, 238.0))
        x2 = draw(st.floats(x1 + 0.01, 320.0))
        y2 = draw(st.floats(y1 + 0.01, 240.0))
        colour = draw(st.none() | st.tuples(*[st.floats(0.0, 255.0)] * 3))
        out.append(
            Detection(
                label=draw(st.sampled_from(LABELS)),
                class_id=0,
                confidence=draw(st.floats(0.0, 1.0)),
                box=(x1, y1, x2, y2),
                color=colour,
            )
        )
    return tuple(out)


@st.composite
def views(draw) -> VisitedView:
    lat = draw(st.integers(0, 12))
    size = GRID.grid().ring_size(lat)
    pose = PoseQuery(lat=lat, lon=draw(st.integers(0, size - 1)))
    return VisitedView(pose=pose, image_size=(320, 240), detections=draw(detections()))


@pytest.mark.parametrize("strategy", ["simple", "paper", "reprojection"])
@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), database=None)
@given(data=st.data())
def test_planning_never_crashes(strategy, data):
    target = data.draw(detections(max_size=6).filter(bool))
    history = data.draw(st.lists(views(), max_size=3))
    request = NextPoseRequest(
        strategy=strategy,
        camera=CAMERA,
        grid=GRID,
        target=TargetImage(image_size=(320, 240), detections=target),
        history=tuple(history),
    )
    try:
        answer = next_pose(request, CONTEXT)
    except ServiceError as exc:  # a 4xx with a reason is fine, a crash is not
        refused = exc.status
    else:
        refused = None
    if refused is not None:
        assert 400 <= refused < 500
        return
    if answer.done:
        assert answer.move == "stay"
    if answer.estimate is not None:
        assert 0.0 <= answer.estimate.confidence <= 1.0


@pytest.mark.parametrize("method", ["exact", "paper"])
@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), database=None)
@given(dets=detections(), theta=st.floats(0.0, 90.0), phi=st.floats(-720.0, 720.0))
def test_mapping_never_crashes(method, dets, theta, phi):
    request = MapRequest(
        camera=CAMERA,
        pose=Pose(theta_deg=theta, phi_deg=phi),
        method=method,
        view=ImageDetections(image_size=(320, 240), detections=dets),
    )
    answer = map_detections(request, CONTEXT.calibrations)
    assert len(answer.objects) == len(dets)
