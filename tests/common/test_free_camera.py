"""The free camera: its orientation forms, its intrinsics, the lens model and its validation."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from services.common.geometry.camera import pinhole_camera, project
from services.common.geometry.free_camera import (
    FreeCamera,
    LensDistortion,
    free_camera_of_pose,
    free_pinhole_camera,
    orbit_position,
    quaternion_of_rotation,
    rotation_of_quaternion,
    rotation_of_yaw_pitch_roll,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.lens import (
    distort,
    fold_radius,
    image_folds,
    invertible_over_film,
    project_lens,
    undistort_pixels,
)
from services.common.geometry.pose import Pose

yaws = st.floats(-720.0, 720.0)
pitches = st.floats(-89.0, 90.0)
rolls = st.floats(-180.0, 180.0)
# Lens coefficients as lenses have them: zero, or of a size that matters.
coefficients = st.one_of(st.just(0.0), st.floats(-1.0, -1e-4), st.floats(1e-4, 1.0))
poses = st.builds(Pose, theta_deg=st.floats(0.0, 90.0), phi_deg=st.floats(-360.0, 360.0))


@settings(max_examples=100, deadline=None)
@given(pose=poses, radius=st.floats(1.0, 50.0))
def test_a_hemisphere_pose_is_the_free_camera_with_its_yaw_and_pitch(pose, radius):
    expected = pinhole_camera(pose, radius, 45.0, 320, 240)
    free = free_pinhole_camera(free_camera_of_pose(pose, radius), 320, 240, 45.0)
    np.testing.assert_allclose(free.rotation, expected.rotation, atol=1e-12)
    np.testing.assert_allclose(free.position, expected.position, atol=1e-12)
    np.testing.assert_allclose(free.translation, expected.translation, atol=1e-11)
    assert (free.fx, free.fy, free.cx, free.cy) == pytest.approx(
        (expected.fx, expected.fy, expected.cx, expected.cy)
    )


@settings(max_examples=100, deadline=None)
@given(yaw=yaws, pitch=pitches, roll=rolls)
def test_yaw_pitch_roll_is_a_rotation_with_the_optical_axis_where_it_says(yaw, pitch, roll):
    rotation = rotation_of_yaw_pitch_roll(yaw, pitch, roll)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    y, p = math.radians(yaw), math.radians(pitch)
    forward = (math.cos(p) * math.cos(y), math.cos(p) * math.sin(y), -math.sin(p))
    np.testing.assert_allclose(rotation[:, 2], forward, atol=1e-12)
    # Roll turns the x axis towards the image's down axis: its height is -cos(pitch) sin(roll).
    expected_dip = -math.cos(p) * math.sin(math.radians(roll))
    assert rotation[2, 0] == pytest.approx(expected_dip, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(yaw=yaws, pitch=pitches, roll=rolls)
def test_yaw_pitch_roll_come_back_from_the_rotation(yaw, pitch, roll):
    rotation = rotation_of_yaw_pitch_roll(yaw, pitch, roll)
    back = yaw_pitch_roll_of_rotation(rotation)
    np.testing.assert_allclose(rotation_of_yaw_pitch_roll(*back), rotation, atol=1e-9)
    if abs(pitch) < 89.99:  # the angles themselves, up to whole turns, away from the poles
        assert back[1] == pytest.approx(pitch, abs=1e-9)
        for got, want in ((back[0], yaw), (back[2], roll)):
            assert math.remainder(got - want, 360.0) == pytest.approx(0.0, abs=1e-7)


def test_a_nadir_view_looks_down_with_the_image_top_along_the_yaw():
    rotation = rotation_of_yaw_pitch_roll(30.0, 90.0, 0.0)
    np.testing.assert_allclose(rotation[:, 2], (0.0, 0.0, -1.0), atol=1e-12)
    up = -rotation[:, 1]
    np.testing.assert_allclose(
        up, (math.cos(math.radians(30)), math.sin(math.radians(30)), 0), atol=1e-12
    )


def test_roll_turns_the_world_in_the_image_counter_clockwise():
    """A point above the optical axis of a level camera appears, after a roll of 90°, on the
    left of the image: the world turned counter-clockwise, the camera clockwise."""
    base = FreeCamera(position=(0.0, 0.0, 1.0), yaw_deg=0.0, pitch_deg=0.0)
    rolled = base.model_copy(update={"roll_deg": 90.0})
    above = np.array([[5.0, 0.0, 2.0]])
    level, _ = project(above, free_pinhole_camera(base, 100, 100, 60.0))
    turned, _ = project(above, free_pinhole_camera(rolled, 100, 100, 60.0))
    assert level[0, 0] == pytest.approx(50.0)
    assert level[0, 1] < 50.0
    assert turned[0, 0] < 50.0
    assert turned[0, 1] == pytest.approx(50.0)


@settings(max_examples=100, deadline=None)
@given(yaw=yaws, pitch=pitches, roll=rolls)
def test_the_three_orientation_forms_agree(yaw, pitch, roll):
    position = (1.0, -2.0, 3.0)
    by_angles = FreeCamera(position=position, yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll)
    rotation = by_angles.rotation()
    quaternion = quaternion_of_rotation(rotation)
    assert math.hypot(*quaternion) == pytest.approx(1.0)
    by_quaternion = FreeCamera(position=position, quaternion_wxyz=quaternion)
    target = tuple(np.asarray(position) + 4.0 * rotation[:, 2])
    by_look_at = FreeCamera(position=position, look_at=target, roll_deg=roll)
    np.testing.assert_allclose(by_quaternion.rotation(), rotation, atol=1e-9)
    if abs(pitch) < 89.99:  # a vertical look-at has no yaw: it takes 0
        np.testing.assert_allclose(by_look_at.rotation(), rotation, atol=1e-9)


def test_a_vertical_look_at_takes_yaw_zero():
    down = FreeCamera(position=(1.0, 2.0, 5.0), look_at=(1.0, 2.0, 0.0), roll_deg=20.0)
    nadir = FreeCamera(position=(1.0, 2.0, 5.0), yaw_deg=0.0, pitch_deg=90.0, roll_deg=20.0)
    np.testing.assert_allclose(down.rotation(), nadir.rotation(), atol=1e-12)


def test_a_quaternion_of_any_length_and_sign_is_the_same_rotation():
    q = np.array([0.3, -0.5, 0.2, 0.7])
    expected = rotation_of_quaternion(q / np.linalg.norm(q))
    np.testing.assert_allclose(rotation_of_quaternion(3.0 * q), expected, atol=1e-12)
    np.testing.assert_allclose(rotation_of_quaternion(-q), expected, atol=1e-12)


def test_pixel_intrinsics_and_their_defaults():
    camera = FreeCamera(position=(0, 0, 5), yaw_deg=0, pitch_deg=90, fx_px=300.0, fy_px=310.0)
    pinhole = free_pinhole_camera(camera, 320, 240, 45.0)
    assert (pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy) == (300.0, 310.0, 160.0, 120.0)
    assert pinhole.fov_deg == pytest.approx(2 * math.degrees(math.atan(160 / 300)))
    scene_fov = free_pinhole_camera(
        camera.model_copy(update={"fx_px": None, "fy_px": None}), 320, 240, 45.0
    )
    assert scene_fov.fov_deg == 45.0


BAD = [
    ({"quaternion_wxyz": (0, 0, 0, 0)}, "quaternion_wxyz"),
    ({"quaternion_wxyz": (1e-9, 0, 0, 0)}, "quaternion_wxyz"),
    ({"look_at": (1.0, 2.0, 3.0)}, "look_at"),
    ({"yaw_deg": 0.0, "pitch_deg": 91.0}, "pitch_deg"),
    ({"yaw_deg": math.nan, "pitch_deg": 0.0}, "yaw_deg"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fov_deg": 0.0}, "fov_deg"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fov_deg": 180.0}, "fov_deg"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fx_px": 0.0, "fy_px": 10.0}, "fx_px"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fx_px": 10.0, "fy_px": -1.0}, "fy_px"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fx_px": math.inf, "fy_px": 1.0}, "fx_px"),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "distortion": {"k1": math.nan}}, "distortion.k1"),
    ({"yaw_deg": 0.0}, ""),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "look_at": (0, 0, 0)}, ""),
    ({"quaternion_wxyz": (1, 0, 0, 0), "roll_deg": 5.0}, ""),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fov_deg": 40.0, "fx_px": 1.0, "fy_px": 1.0}, ""),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "fx_px": 1.0}, ""),
    ({"yaw_deg": 0.0, "pitch_deg": 0.0, "cx_px": 1.0}, ""),
]


@pytest.mark.parametrize(("fields", "where"), BAD)
def test_bad_cameras_are_refused_naming_the_field(fields, where):
    with pytest.raises(ValidationError) as info:
        FreeCamera.model_validate({"position": (1.0, 2.0, 3.0), **fields})
    loc = ".".join(str(p) for p in info.value.errors()[0]["loc"])
    assert loc == where, info.value


# -- the lens ------------------------------------------------------------------------------------

LENSES = [
    LensDistortion(k1=-0.25, k2=0.05),
    LensDistortion(k1=0.1, k2=0.01, p1=0.002, p2=-0.003),
    LensDistortion(p1=0.01),
    # a drone's calibrated lens (DJI's DewarpData order), k3 included
    LensDistortion(k1=-0.269, k2=0.116, p1=-8.8e-5, p2=-3.1e-4, k3=-0.0358),
]


@pytest.mark.parametrize("lens", LENSES, ids=str)
def test_the_lens_projects_as_opencv(lens):
    camera = FreeCamera(position=(0.5, -1.0, 6.0), look_at=(0.0, 0.0, 0.0), roll_deg=10.0)
    pinhole = free_pinhole_camera(
        camera.model_copy(update={"fx_px": 280.0, "fy_px": 300.0, "cx_px": 150.0, "cy_px": 130.0}),
        320,
        240,
        45.0,
    )
    rng = np.random.default_rng(3)
    points = rng.uniform(-2.0, 2.0, size=(40, 3))
    ours, _ = project_lens(points, pinhole, lens)
    rvec, _ = cv2.Rodrigues(np.asarray(pinhole.rotation))
    matrix = np.array([[280.0, 0, 150.0], [0, 300.0, 130.0], [0, 0, 1]])
    theirs, _ = cv2.projectPoints(
        points, rvec, np.asarray(pinhole.translation), matrix, lens.coefficients()
    )
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("lens", LENSES, ids=str)
def test_undistortion_inverts_the_lens(lens):
    pinhole = free_pinhole_camera(
        FreeCamera(position=(0, 0, 5), yaw_deg=0, pitch_deg=90), 320, 240, 60.0
    )
    rng = np.random.default_rng(5)
    pixels = rng.uniform((0, 0), (320, 240), size=(100, 2))
    xy = undistort_pixels(pixels, pinhole, lens)
    back = distort(xy, lens) * (pinhole.fx, pinhole.fy) + (pinhole.cx, pinhole.cy)
    np.testing.assert_allclose(back, pixels, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(k1=coefficients, k2=coefficients, k3=coefficients)
def test_the_fold_radius_is_where_the_radial_model_stops_increasing(k1, k2, k3):
    r_star = fold_radius(LensDistortion(k1=k1, k2=k2, k3=k3))
    slope = lambda r: 1 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6  # noqa: E731
    if math.isinf(r_star):
        assert all(slope(r) > 0 for r in np.linspace(0, 10, 200))
    else:
        scale = 1 + abs(3 * k1 * r_star**2) + abs(5 * k2 * r_star**4) + abs(7 * k3 * r_star**6)
        assert slope(r_star) / scale == pytest.approx(0.0, abs=1e-9)
        assert all(slope(r) > 0 for r in np.linspace(0, r_star, 50)[:-1])


def test_a_lens_takes_opencv_s_four_or_five_coefficients():
    assert LensDistortion.of_coefficients([-0.2, 0.05, 0.001, 0.002]) == LensDistortion(
        k1=-0.2, k2=0.05, p1=0.001, p2=0.002
    )
    five = LensDistortion.of_coefficients([-0.2, 0.05, 0.001, 0.002, -0.01])
    assert five.k3 == -0.01
    np.testing.assert_array_equal(five.coefficients(), [-0.2, 0.05, 0.001, 0.002, -0.01])
    assert not LensDistortion(k3=1e-6).is_zero
    for count in (3, 6):
        with pytest.raises(ValueError, match="4 or 5 numbers"):
            LensDistortion.of_coefficients([0.0] * count)


def test_a_strong_barrel_distortion_folds_a_wide_film():
    pinhole = free_pinhole_camera(
        FreeCamera(position=(0, 0, 5), yaw_deg=0, pitch_deg=90, fov_deg=90.0), 320, 240, 90.0
    )
    # The corner's normalised radius is 1.25. k1 = -0.05: r* = sqrt(1 / 0.15) ≈ 2.58 and
    # r_d(r*) = 2 r* / 3 ≈ 1.72 lies beyond it; k1 = -0.1: r_d(r*) ≈ 1.22 does not.
    assert not image_folds(pinhole, LensDistortion(k1=-0.05))
    assert image_folds(pinhole, LensDistortion(k1=-0.1))
    assert not image_folds(pinhole, LensDistortion(k1=0.5, k2=0.1))
    # k3 alone: r* = (1 / 0.7)^(1/6) ≈ 1.06 and r_d(r*) = 6 r* / 7 ≈ 0.91, inside the corner
    assert image_folds(pinhole, LensDistortion(k3=-0.1))
    assert not image_folds(pinhole, LensDistortion(k3=-0.01))


def test_a_lens_just_short_of_folding_has_no_inverse_at_the_corners():
    """k3 bends the radial model back just beyond the film's corners (reach 1.080 against a
    corner at 1.078): it does not fold, but the corners' undistortion does not converge."""
    film = free_pinhole_camera(
        FreeCamera(
            position=(0, 0, 5), yaw_deg=0, pitch_deg=90, fx_px=374.67, fy_px=374.67
        ).model_copy(update={"cx_px": 315.25, "cy_px": 239.99}),
        640,
        480,
        81.0,
    )
    near = LensDistortion(k1=-0.00891, k2=0.00287, p1=4.28e-4, p2=-4.30e-4, k3=-0.03408)
    assert not image_folds(film, near)
    assert not invertible_over_film(film, near)
    assert invertible_over_film(film, LensDistortion(k1=-0.1, k2=0.01, k3=-0.002))
    assert not invertible_over_film(film, LensDistortion(k1=-0.9))  # folds
    assert invertible_over_film(film, LensDistortion())


@pytest.mark.parametrize(("elevation", "azimuth"), [(10.0, 0.0), (45.0, 123.0), (90.0, 300.0)])
def test_an_orbit_position_looks_back_at_its_point(elevation, azimuth):
    """From ``orbit_position``, yaw α + 180° and pitch ε put the looked-at point at the image
    centre, at the given distance."""
    look = (1.0, -2.0, 0.5)
    position = orbit_position(look, 4.0, elevation, azimuth)
    assert math.dist(position, look) == pytest.approx(4.0)
    camera = FreeCamera(
        position=position, yaw_deg=azimuth + 180.0, pitch_deg=elevation, fov_deg=60.0
    )
    pinhole = free_pinhole_camera(camera, 320, 240, 60.0)
    cam = np.asarray(pinhole.rotation) @ np.asarray(look) + np.asarray(pinhole.translation)
    u, v = pinhole.fx * cam[0] / cam[2] + pinhole.cx, pinhole.fy * cam[1] / cam[2] + pinhole.cy
    assert cam[2] == pytest.approx(4.0)
    assert (u, v) == pytest.approx((160.0, 120.0))
