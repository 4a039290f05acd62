"""The pose from boxes alone against the renderer's ground truth: free cameras annotated by the
real engine at 160x120 (the objects' visible boxes, as a perfect detector would draw them,
pixel-quantised), solved by services.optimizer.free. The bounds are the first run's figures
rounded up, per case; the box-only bound of the issue (49 % within 2 %/1° at 320x240 with
0.7 px noise) says some views cannot do better."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import FreeCamera
from services.optimizer.free import Intrinsics, scene_objects, solve_free_pose
from services.renderer.view import resolve_free_camera

W, H = 160, 120
MIN_VISIBLE = 0.6


def annotated(engine, catalog, scene_id: str, camera: FreeCamera):
    scene = catalog.get(scene_id)
    view = resolve_free_camera(scene, camera, W, H)
    annotations = engine.annotate(scene, view, W, H, None)
    objects = scene_objects(scene.spec, scene.assets)
    detections = [
        Detection(label=objects.labels[i], class_id=i, confidence=0.9, box=obj.box)
        for i, obj in enumerate(annotations.objects)
        if obj.box is not None and obj.visible_fraction >= MIN_VISIBLE
    ]
    return objects, annotations, detections


def errors(pose, camera) -> tuple[float, float]:
    moved = float(np.linalg.norm(np.asarray(pose.position) - camera.position))
    relative = pose.rotation() @ np.asarray(camera.rotation)
    turned = math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
    return moved, turned


# (scene, camera, position bound as a share of the radius, rotation bound in degrees); measured
# first: 0.35 %/0.20°, 0.46 %/0.19°, 1.11 %/0.58°, 4.0 %/2.1°.
CASES = [
    ("demo", FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0)), 0.02, 1.0),
    (
        "garden",
        FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0),
        0.02,
        1.0,
    ),
    ("garden", FreeCamera(position=(0.3, 0.2, 9.0), yaw_deg=30.0, pitch_deg=90.0), 0.02, 1.0),
    # Five balls of one size, straight down: every centre at one height, so a small tilt and a
    # shift trade off within the boxes' pixel quantisation (0.24 px RMS at the answer).
    ("demo", FreeCamera(position=(0.3, 0.2, 9.0), yaw_deg=30.0, pitch_deg=90.0), 0.05, 3.0),
]
NADIR = 2
"""From this case on the views look straight down, which boxes pin only loosely: the best pose
is within its bounds, but the answer is ``ambiguous``, not ``found``."""


@pytest.mark.parametrize(
    ("scene_id", "camera", "max_position", "max_rotation_deg", "status"),
    [(*case, "found" if i < NADIR else "ambiguous") for i, case in enumerate(CASES)],
)
def test_rendered_boxes_give_the_camera(
    engine, catalog, scene_id, camera, max_position, max_rotation_deg, status
):
    objects, annotations, detections = annotated(engine, catalog, scene_id, camera)
    truth = annotations.camera
    # the point sets stand where the renderer puts the objects (meshes placed from their PLY)
    centroids = np.array([obj.centroid for obj in annotations.objects])
    assert np.allclose(objects.centroids, centroids, atol=1e-5)
    intrinsics = Intrinsics(truth.fx, truth.fy, truth.cx, truth.cy)
    answer = solve_free_pose(objects, detections, W, H, intrinsics)
    assert answer.status == status, answer.reason
    moved, turned = errors(answer.pose, truth)
    assert moved < max_position * objects.radius
    assert turned < max_rotation_deg
    assert answer.pose.residual_px < 1.0
    for pair in answer.pose.correspondences:
        assert pair.object == objects.names[detections[pair.detection].class_id]


def test_rendered_boxes_give_the_focal_length_when_not_given(engine, catalog):
    """A rolled view through a lens 20 % wider than the scene camera's; measured first:
    0.77 %/0.09°, fov 54.45° (0.8 % off)."""
    camera = FreeCamera(
        position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0, fov_deg=54.0
    )
    objects, annotations, detections = annotated(engine, catalog, "garden", camera)
    answer = solve_free_pose(objects, detections, W, H)
    assert answer.status == "found", answer.reason
    assert answer.pose.intrinsics.source == "estimated"
    assert answer.pose.intrinsics.fov_deg == pytest.approx(54.0, rel=0.03)
    moved, turned = errors(answer.pose, annotations.camera)
    assert moved < 0.05 * objects.radius
    assert turned < 2.0


def test_the_answer_renders_the_targets_boxes(engine, catalog):
    """The answer as the renderer's free camera (quaternion, fx/fy/cx/cy) annotates the target's
    boxes again: what the one confirming render of item 2 will compare."""
    camera = FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0)
    objects, annotations, detections = annotated(engine, catalog, "garden", camera)
    answer = solve_free_pose(objects, detections, W, H)
    assert answer.status == "found", answer.reason
    _, again, _ = annotated(engine, catalog, "garden", answer.pose.free_camera())
    for pair in answer.pose.correspondences:
        target = np.asarray(detections[pair.detection].box)
        rendered = np.asarray(again.objects[objects.names.index(pair.object)].box)
        assert np.sqrt(np.mean((rendered - target) ** 2)) < 1.5
