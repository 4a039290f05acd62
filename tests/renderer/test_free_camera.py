"""Free cameras through the real render engine: the same images and ground truth as a grid pose
where they coincide, and annotations that follow the camera maths (principal point, roll, nadir,
distortion). Small films, few samples."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.common.errors import UnprocessableError
from services.common.geometry.free_camera import (
    FreeCamera,
    LensDistortion,
    free_camera_of_pose,
    quaternion_of_rotation,
)
from services.common.geometry.pose import Pose
from services.renderer.view import resolve_free_camera

W, H = 160, 120
SPP = 4
POSE = Pose(theta_deg=37.5, phi_deg=120.0)


def free_view(catalog, camera: FreeCamera, scene: str = "demo", width: int = W, height: int = H):
    return resolve_free_camera(catalog.get(scene), camera, width, height)


def render(engine, catalog, camera: FreeCamera, scene: str = "demo", **film):
    width, height = film.get("width", W), film.get("height", H)
    view = free_view(catalog, camera, scene, width, height)
    return engine.render(catalog.get(scene), view, width, height, SPP, seed=3).rgb


def annotate(engine, catalog, camera: FreeCamera, scene: str = "demo", **film):
    width, height = film.get("width", W), film.get("height", H)
    view = free_view(catalog, camera, scene, width, height)
    return engine.annotate(catalog.get(scene), view, width, height, None)


def opencv_projection(ann) -> np.ndarray:
    """The objects' centroids through ``cv2.projectPoints`` with the annotated camera and lens."""
    camera = ann.camera
    rvec, _ = cv2.Rodrigues(np.asarray(camera.rotation))
    matrix = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    coefficients = ann.distortion.coefficients() if ann.distortion else np.zeros(4)
    centroids = np.array([o.centroid for o in ann.objects])
    pixels, _ = cv2.projectPoints(
        centroids, rvec, np.asarray(camera.translation), matrix, coefficients
    )
    return pixels.reshape(-1, 2)


def assert_centres_follow_the_projection(ann, tolerance_px: float = 1.0) -> int:
    """Projected centres are OpenCV's projection; each fully seen sphere's box is centred on its
    projected centre (a sphere's silhouette is symmetric about it only without distortion, so
    ``tolerance_px`` is looser there). Returns how many boxes were compared."""
    expected = opencv_projection(ann)
    checked = 0
    for obj, (u, v) in zip(ann.objects, expected, strict=True):
        assert obj.projected_center == pytest.approx((u, v), abs=1e-6)
        if obj.box is None or obj.visible_fraction < 1.0:
            continue
        x1, y1, x2, y2 = obj.box
        if x1 <= 0 or y1 <= 0 or x2 >= ann.camera.width or y2 >= ann.camera.height:
            continue
        assert x1 <= u <= x2, obj
        assert y1 <= v <= y2, obj
        assert abs((x1 + x2) / 2 - u) < tolerance_px, obj
        assert abs((y1 + y2) / 2 - v) < tolerance_px, obj
        checked += 1
    return checked


@pytest.mark.parametrize(
    "pose",
    [POSE, Pose(theta_deg=0.0, phi_deg=200.0), Pose(theta_deg=82.5, phi_deg=310.0)],
    ids=str,
)
def test_a_free_camera_at_a_grid_pose_is_that_pose(engine, catalog, pose):
    scene = catalog.get("demo")
    camera = free_camera_of_pose(pose, scene.spec.camera.radius)
    expected = engine.render(scene, pose, W, H, SPP, seed=3).rgb
    differs = np.abs(render(engine, catalog, camera).astype(int) - expected.astype(int)) > 0
    assert differs.mean() < 0.001  # the same rays, up to the last bit of the pose's rounding
    grid = engine.annotate(scene, pose, W, H, None)
    free = annotate(engine, catalog, camera)
    assert free.pose is None
    assert free.distortion is None
    for key in ("rotation", "translation", "position"):
        np.testing.assert_allclose(getattr(free.camera, key), getattr(grid.camera, key), atol=1e-12)
    intrinsics = ("width", "height", "fov_deg", "fx", "fy", "cx", "cy")
    assert free.camera.model_dump(include=set(intrinsics)) == pytest.approx(
        grid.camera.model_dump(include=set(intrinsics))
    )
    for a, b in zip(free.objects, grid.objects, strict=True):
        assert (a.box, a.full_box, a.visible_pixels) == (b.box, b.full_box, b.visible_pixels)
        assert a.projected_center == pytest.approx(b.projected_center, abs=1e-9)


def test_the_orientation_forms_of_one_camera_render_the_same_image(engine, catalog):
    position = (3.0, -2.0, 2.5)
    target = (0.2, 0.4, 0.3)
    by_look_at = FreeCamera(position=position, look_at=target, roll_deg=15.0)
    rotation = by_look_at.rotation()
    by_quaternion = FreeCamera(position=position, quaternion_wxyz=quaternion_of_rotation(rotation))
    forward = rotation[:, 2]
    yaw = float(np.degrees(np.arctan2(forward[1], forward[0])))
    pitch = float(np.degrees(np.arcsin(-forward[2])))
    by_angles = FreeCamera(position=position, yaw_deg=yaw, pitch_deg=pitch, roll_deg=15.0)
    reference = render(engine, catalog, by_look_at)
    for other in (by_quaternion, by_angles):
        image = render(engine, catalog, other)
        differs = np.abs(image.astype(int) - reference.astype(int)) > 2
        assert differs.mean() < 0.002  # rounding of the pose flips a few edge pixels at most


@pytest.mark.parametrize(
    "camera",
    [
        FreeCamera(position=(0.2, 0.1, 7.0), yaw_deg=25.0, pitch_deg=90.0),
        FreeCamera(position=(5.0, 3.0, 3.0), look_at=(0.0, 0.5, 0.0), roll_deg=30.0),
        FreeCamera(position=(-4.0, -1.0, 2.0), look_at=(0.5, 0.5, 0.4), roll_deg=-20.0),
    ],
    ids=["nadir", "rolled", "rolled-low"],
)
def test_nadir_and_rolled_views_annotate_as_the_camera_projects(engine, catalog, camera):
    ann = annotate(engine, catalog, camera)
    assert assert_centres_follow_the_projection(ann) >= 2
    image = render(engine, catalog, camera)
    assert image.shape == (H, W, 3)


def test_pixel_intrinsics_equal_to_the_fov_render_the_same_image(engine, catalog):
    camera = FreeCamera(position=(4.0, -3.0, 4.0), look_at=(0.0, 0.0, 0.3), fov_deg=50.0)
    focal = (W / 2) / np.tan(np.radians(25.0))
    in_pixels = camera.model_copy(
        update={"fov_deg": None, "fx_px": focal, "fy_px": focal, "cx_px": W / 2, "cy_px": H / 2}
    )
    assert np.array_equal(render(engine, catalog, in_pixels), render(engine, catalog, camera))


def test_a_principal_point_shift_moves_the_annotations_with_it(engine, catalog):
    base = FreeCamera(
        position=(0.0, 0.5, 8.0), yaw_deg=90.0, pitch_deg=90.0, fx_px=150.0, fy_px=150.0
    )
    shifted = base.model_copy(update={"cx_px": W / 2 + 12.0, "cy_px": H / 2 - 7.0})
    a = annotate(engine, catalog, base)
    b = annotate(engine, catalog, shifted)
    assert assert_centres_follow_the_projection(b) >= 3
    moved = 0
    for one, two in zip(a.objects, b.objects, strict=True):
        du = two.projected_center[0] - one.projected_center[0]
        dv = two.projected_center[1] - one.projected_center[1]
        assert (du, dv) == pytest.approx((12.0, -7.0), abs=1e-9)
        if one.visible_fraction == 1.0 == two.visible_fraction and one.box and two.box:
            inside = all(0 < c for c in one.box + two.box) and max(one.box[2], two.box[2]) < W
            if inside and max(one.box[3], two.box[3]) < H:
                shift = np.subtract(two.box, one.box)
                np.testing.assert_allclose(shift, (12, -7, 12, -7), atol=1.0)
                moved += 1
    assert moved >= 2


def test_a_principal_point_shift_moves_the_image_with_it(engine, catalog):
    scene = catalog.get("demo")
    base = FreeCamera(position=(0.0, 0.5, 8.0), yaw_deg=90, pitch_deg=90, fx_px=150, fy_px=150)
    shifted = base.model_copy(update={"cx_px": W / 2 + 12.0, "cy_px": H / 2 - 7.0})
    # Blurred: the lit ground's sampling noise at 16 spp is larger than a shift's difference.
    a, b = (
        cv2.GaussianBlur(
            engine.render(scene, free_view(catalog, cam), W, H, 16, seed=1).rgb.astype(np.float32),
            (0, 0),
            3,
        )
        for cam in (base, shifted)
    )
    aligned = np.abs(b[:-7, 12:] - a[7:, :-12]).mean()  # content 12 px right, 7 px up
    unaligned = np.abs(b[:-7, 12:] - a[:-7, 12:]).mean()
    assert aligned < 3.0
    assert unaligned > 3 * aligned


def test_a_lens_warp_is_computed_once_for_every_pose_through_it(catalog):
    lens = LensDistortion(k1=-0.1, p2=0.001)
    first, second = (
        free_view(
            catalog,
            FreeCamera(
                position=(x, 0.0, 5.0), yaw_deg=0, pitch_deg=70, fov_deg=50, distortion=lens
            ),
        )
        for x in (0.0, 1.0)
    )
    assert first.camera.position != second.camera.position
    assert first.map_x is second.map_x  # the cache's hit: the same arrays, read-only
    assert not first.map_x.flags.writeable
    assert first.rendered.width == second.rendered.width


def test_a_warped_film_is_padded_to_its_step_and_shows_the_same_image(engine, catalog, monkeypatch):
    """Lenses of about the same extent render on one padded film size (the engine loads the
    scene once per size), and the padding moves no ray: the ground truth is the same as on the
    film planned unpadded."""
    from services.renderer import free_view as planning

    lenses = [LensDistortion(k1=k1) for k1 in (-0.04, -0.05, -0.06)]
    camera = FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0), fov_deg=60.0)
    padded = [free_view(catalog, camera.model_copy(update={"distortion": k})) for k in lenses]
    films = {(v.rendered.width, v.rendered.height) for v in padded}
    assert len(films) == 1
    width, height = films.pop()
    assert width % planning.FILM_STEP_PX == 0
    assert height % planning.FILM_STEP_PX == 0
    lensed = camera.model_copy(update={"distortion": lenses[0]})
    with_padding = annotate(engine, catalog, lensed)
    monkeypatch.setattr(planning, "FILM_STEP_PX", 1)
    planning._WARPS.clear()
    try:
        unpadded = free_view(catalog, lensed)
        assert unpadded.rendered.width < width
        without = annotate(engine, catalog, lensed)
    finally:
        planning._WARPS.clear()
    boxes = [o.box for o in with_padding.objects]
    assert any(b is not None for b in boxes)
    assert boxes == [o.box for o in without.objects]


def test_unequal_focal_lengths_render_through_a_warp_and_annotate_consistently(engine, catalog):
    camera = FreeCamera(
        position=(0.0, 0.0, 8.0), yaw_deg=0.0, pitch_deg=90.0, fx_px=150.0, fy_px=120.0
    )
    view = free_view(catalog, camera)
    assert view.rendered.fx == view.rendered.fy == 150.0
    ann = annotate(engine, catalog, camera)
    assert assert_centres_follow_the_projection(ann, tolerance_px=1.0) >= 3
    assert render(engine, catalog, camera).shape == (H, W, 3)


@pytest.mark.parametrize(
    "lens",
    [LensDistortion(k1=-0.3, k2=0.08), LensDistortion(k1=0.15, p1=0.004, p2=-0.003)],
    ids=["barrel", "pincushion-tangential"],
)
def test_distorted_annotations_follow_the_distorted_projection(engine, catalog, lens):
    pinhole = FreeCamera(
        position=(0.3, -0.2, 4.5), yaw_deg=10.0, pitch_deg=90.0, fx_px=80.0, fy_px=80.0
    )
    camera = pinhole.model_copy(update={"distortion": lens})
    ann = annotate(engine, catalog, camera)
    assert ann.distortion == lens
    # A sphere's distorted silhouette is no longer symmetric about its centre's image: a pixel.
    assert assert_centres_follow_the_projection(ann, tolerance_px=1.5) >= 2
    undistorted = annotate(engine, catalog, pinhole)
    shifts = [
        np.hypot(*np.subtract(a.projected_center, b.projected_center))
        for a, b in zip(ann.objects, undistorted.objects, strict=True)
    ]
    assert max(shifts) > 2.0  # the lens does move the objects
    image = render(engine, catalog, camera)
    assert image.shape == (H, W, 3)
    assert image.std() > 10  # an image, not a border colour


def test_a_camera_inside_an_object_is_refused_by_the_engine(engine, catalog):
    scene = catalog.get("demo")
    red = scene.spec.objects[0]
    inside = FreeCamera(position=(red.position[0], red.position[1], 0.4), yaw_deg=0, pitch_deg=0)
    view = free_view(catalog, inside)
    for work in (
        lambda: engine.render(scene, view, W, H, 1),
        lambda: engine.annotate(scene, view, W, H, None),
    ):
        with pytest.raises(UnprocessableError) as info:
            work()
        assert info.value.field == "camera.position"


def test_frozen_free_camera_renders_are_the_traced_renders(engine, traced_engine, catalog):
    """The fov and the principal point are sensor parameters the frozen render must take as
    inputs: free cameras that change them (directly or through a warp), and a grid pose after
    them, give the very pixels of tracing each again."""
    scene = catalog.get("garden")
    cameras = [
        FreeCamera(position=(3.0, 2.0, 4.0), look_at=(0, 0, 0), fov_deg=60.0),
        FreeCamera(position=(3.0, 2.0, 4.0), look_at=(0, 0, 0), fov_deg=30.0),
        FreeCamera(position=(0.0, 1.0, 6.0), yaw_deg=0, pitch_deg=80, fx_px=90, fy_px=90, cx_px=70),
        FreeCamera(
            position=(0.0, 1.0, 6.0),
            yaw_deg=0,
            pitch_deg=80,
            fx_px=90,
            fy_px=90,
            distortion=LensDistortion(k1=-0.1),
        ),
    ]
    views = [free_view(catalog, c, "garden") for c in cameras]
    views.append(Pose(theta_deg=30, phi_deg=40))
    for view in views:
        frozen = engine.render(scene, view, W, H, 2, seed=4)
        again = traced_engine.render(scene, view, W, H, 2, seed=4)
        assert np.array_equal(frozen.rgb, again.rgb), view


def test_objects_behind_a_free_camera_have_no_projected_centre(engine, catalog):
    """A camera at the scene's edge looking out: every object is at its back; their annotations
    say so (no box, no projected centre) instead of failing on a NaN projection."""
    camera = FreeCamera(position=(4.0, 0.0, 1.5), look_at=(9.0, 0.0, 0.0), fov_deg=50.0)
    ann = annotate(engine, catalog, camera)
    behind = ann.camera.rotation[2]
    for obj in ann.objects:
        depth = float(np.dot(behind, obj.centroid) + ann.camera.translation[2])
        assert depth < 0.0
        assert obj.projected_center is None
        assert obj.box is None
