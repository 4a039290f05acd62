"""The camera's attitude a photo states (its drone's gimbal pitch and roll) in the box solve
(:mod:`services.optimizer.free.solve`): poses whose down direction lies far from it are never
answered, nor offered as rivals or alternatives; a pose that keeps to it is unchanged."""

from __future__ import annotations

import math

import pytest

from services.common.geometry.free_camera import (
    FreeCamera,
    attitude_error_deg,
    free_pinhole_camera,
    rotation_of_quaternion,
    yaw_pitch_roll_of_rotation,
)
from services.optimizer.free import SceneObjects, scene_objects, solve_free_pose
from services.optimizer.free.solve import ATTITUDE_TOLERANCE_DEG
from tests.optimizer.test_free_pose import CAMERAS, H, W, errors, exact_detections, intrinsics_of


@pytest.fixture(scope="module")
def demo(catalog) -> SceneObjects:
    scene = catalog.get("demo")
    return scene_objects(scene.spec, scene.assets)


def attitude_of(camera: FreeCamera) -> tuple[float, float]:
    _, pitch, roll = yaw_pitch_roll_of_rotation(camera.rotation())
    return pitch, roll


def off_attitude(pose, attitude: tuple[float, float]) -> float:
    return attitude_error_deg(rotation_of_quaternion(pose.quaternion_wxyz), *attitude)


@pytest.mark.parametrize(
    ("yaw", "pitch", "roll"), [(0.0, 30.0, 0.0), (123.0, 60.0, 15.0), (250.0, 89.0, -40.0)]
)
def test_the_attitude_error_leaves_the_heading_out(yaw, pitch, roll):
    rotation = FreeCamera(
        position=(0, 0, 5), yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll
    ).rotation()
    assert attitude_error_deg(rotation, pitch, roll) == pytest.approx(0.0, abs=1e-6)
    # a level camera pitched 10° further: 10° off, whatever its heading
    level = FreeCamera(position=(0, 0, 5), yaw_deg=yaw, pitch_deg=pitch - 10.0).rotation()
    assert attitude_error_deg(level, pitch, 0.0) == pytest.approx(10.0, abs=1e-6)
    # at the nadir, roll and yaw are one turn about the vertical: no attitude error
    nadir = FreeCamera(position=(0, 0, 5), yaw_deg=yaw, pitch_deg=90.0).rotation()
    assert attitude_error_deg(nadir, 90.0, roll) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("name", ["hemisphere", "rolled", "nadir"])
def test_the_true_attitude_keeps_the_answer(demo, name):
    objects = demo
    camera = CAMERAS[name]
    pinhole = free_pinhole_camera(camera, W, H, objects.fov_deg)
    dets = exact_detections(objects, pinhole)
    plain = solve_free_pose(objects, dets, W, H, intrinsics_of(pinhole))
    attitude = attitude_of(camera)
    kept = solve_free_pose(objects, dets, W, H, intrinsics_of(pinhole), attitude=attitude)
    assert plain.pose is not None
    assert off_attitude(plain.pose, attitude) < 1.0
    assert (kept.status, kept.ambiguity, kept.pose) == (plain.status, plain.ambiguity, plain.pose)


def test_a_pose_far_from_the_stated_attitude_is_not_answered(demo):
    objects = demo
    camera = CAMERAS["hemisphere"]
    pinhole = free_pinhole_camera(camera, W, H, objects.fov_deg)
    pitch, roll = attitude_of(camera)
    answer = solve_free_pose(
        objects, exact_detections(objects, pinhole), W, H, intrinsics_of(pinhole),
        attitude=(pitch + 25.0, roll),
    )  # fmt: skip
    assert answer.status == "ambiguous"
    assert answer.ambiguity == "attitude"
    assert "pitch and roll the photo states" in answer.reason
    assert answer.pose is not None
    # the pose the boxes give is still the true one: the photo's attitude is what is off
    moved, turned = errors(answer.pose, pinhole)
    assert moved < 0.01 * objects.radius
    assert turned < 0.5


def test_two_boxes_keep_only_poses_of_the_stated_attitude(demo):
    """Two paired boxes allow poses of any tilt; the attitude leaves only those near it."""
    objects = demo
    camera = CAMERAS["hemisphere"]
    pinhole = free_pinhole_camera(camera, W, H, objects.fov_deg)
    dets = exact_detections(objects, pinhole)[:2]
    attitude = attitude_of(camera)
    plain = solve_free_pose(objects, dets, W, H, intrinsics_of(pinhole))
    assert plain.pose is not None
    offs = [off_attitude(p, attitude) for p in (plain.pose, *plain.alternatives)]
    assert max(offs) > ATTITUDE_TOLERANCE_DEG  # without it, poses of other tilts stand
    kept = solve_free_pose(objects, dets, W, H, intrinsics_of(pinhole), attitude=attitude)
    assert kept.status == "ambiguous"
    assert kept.ambiguity == "few"
    assert kept.pose is not None
    for pose in (kept.pose, *kept.alternatives):
        assert off_attitude(pose, attitude) <= ATTITUDE_TOLERANCE_DEG
    assert "ruled out" in kept.reason
    assert math.isfinite(kept.pose.residual_px)
