"""Dense refinement by one render against the renderer's ground truth: the target is a real
render at the true camera, the start a pose a few percent and degrees off (or the box solver's
answer), and the refinement gets one render with depth at the start, as a search would."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.dense_clutter import textured
from cosmos.bench.altered import alter_scene
from services.common.catalog import SceneCatalog
from services.common.contracts.detect import Detection
from services.common.contracts.free import above_chance
from services.common.geometry.free_camera import (
    FreeCamera,
    free_pinhole_camera,
    quaternion_of_rotation,
)
from services.optimizer.free import Intrinsics, scene_objects, solve_free_pose
from services.optimizer.free.chamfer import ChamferProblem
from services.optimizer.free.dense import LEVELS, pyramid, refine_dense
from services.optimizer.free.edges import MIN_SPAN, outline, with_contrast
from services.optimizer.free.focal_bounds import FOCAL_BOUNDS, FocalRange
from services.optimizer.free.refit import worth_another_render
from services.optimizer.refine_pose import MIN_INLIER_SHARE
from services.renderer.view import resolve_free_camera

W, H = 320, 240
SPP = 16
BOX_NOISE_PX = 0.7


def rendered(engine, scene, camera: FreeCamera):
    """The view's RGB, depth and pinhole camera."""
    view = resolve_free_camera(scene, camera, W, H)
    rgb = engine.render(scene, view, W, H, SPP, 0).rgb
    return rgb, engine.depth(scene, view, W, H).depth, view.camera


def gray(rgb):
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def moved(camera: FreeCamera, angle_deg: float, shift: float, seed: int, fov_deg: float):
    """``camera`` turned by ``angle_deg`` about a random axis and moved by ``shift`` units in a
    random direction, with ``fov_deg``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(angle_deg))
    direction = rng.normal(size=3)
    position = np.asarray(camera.position) + shift * direction / np.linalg.norm(direction)
    x, y, z, w = (turn * Rotation.from_matrix(camera.rotation())).as_quat()
    return FreeCamera(position=tuple(position), quaternion_wxyz=(w, x, y, z), fov_deg=fov_deg)


def noisy_boxes(engine, scene, objects, truth: FreeCamera, seed: int):
    """The view's ground truth and, as detections, the boxes of its objects at least 60 %
    visible with the detector's edge noise (:data:`BOX_NOISE_PX`)."""
    annotations = engine.annotate(scene, resolve_free_camera(scene, truth, W, H), W, H, None)
    rng = np.random.default_rng(seed)
    detections = [
        Detection(
            label=objects.labels[i],
            class_id=i,
            confidence=0.9,
            box=tuple(np.clip(np.asarray(obj.box) + rng.normal(0.0, BOX_NOISE_PX, 4), 0, W)),
        )
        for i, obj in enumerate(annotations.objects)
        if obj.box is not None and obj.visible_fraction >= 0.6
    ]
    return annotations, detections


def errors(fit_rotation, fit_position, truth: FreeCamera) -> tuple[float, float]:
    """Position error in scene units and rotation error in degrees (camera-to-world given)."""
    relative = Rotation.from_matrix(np.asarray(fit_rotation).T @ truth.rotation())
    distance = float(np.linalg.norm(np.asarray(fit_position) - truth.position))
    return distance, math.degrees(relative.magnitude())


# (scene, true camera): an oblique view, a nadir view, a rolled view.
VIEWS = [
    ("demo", FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0), fov_deg=45.0)),
    ("demo", FreeCamera(position=(0.3, 0.2, 9.0), yaw_deg=30.0, pitch_deg=90.0, fov_deg=40.0)),
    (
        "garden",
        FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0, fov_deg=50.0),
    ),
]


@pytest.mark.parametrize(("scene_id", "truth"), VIEWS, ids=["oblique", "nadir", "rolled"])
def test_a_pose_a_few_percent_off_is_refined_to_the_true_one(engine, catalog, scene_id, truth):
    """2 % of the radius and 2° off; measured first on demo: 0.1 %/0.06° (oblique), 0.4 %/0.18°
    (nadir)."""
    scene = catalog.get(scene_id)
    radius = scene.spec.camera.radius
    target, _, _ = rendered(engine, scene, truth)
    start = moved(truth, 2.0, 0.02 * radius, seed=3, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=False)
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert distance < 0.006 * radius
    assert angle < 0.3
    assert fit.inliers > 0.8 * fit.points > 100
    assert fit.inliers > fit.start_inliers
    assert fit.residual_px < 1.0


def test_a_hazy_photo_is_refined_as_a_clear_one(engine, catalog):
    """The oblique view's target with its contrast squeezed to a third about its middle (a
    photo's haze or exposure: a span of about 50 grey levels), the start 2 %/2° off: its edges
    are found as the clear target's (:func:`with_contrast`), and the fit lands within the clear
    target's bounds. Without the stretch, most of its steps fell under Canny's thresholds."""
    scene_id, truth = VIEWS[0]
    scene = catalog.get(scene_id)
    radius = scene.spec.camera.radius
    target, _, _ = rendered(engine, scene, truth)
    clear = gray(target)
    hazy = np.clip(np.rint(128.0 + (clear.astype(np.float64) - 128.0) / 3.0), 0, 255)
    hazy = hazy.astype(np.uint8)
    start = moved(truth, 2.0, 0.02 * radius, seed=3, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    fit = refine_dense(hazy, rgb, depth, camera, fit_focal=False)
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert distance < 0.006 * radius  # measured first: 0.43 units (5.4 %) without the stretch
    assert angle < 0.3
    assert fit.inliers > 0.7 * fit.points  # 75 % (the clear target's 96 %)


def test_contrast_is_raised_to_the_least_span_only():
    """A squeezed grey is stretched about its middle to :data:`MIN_SPAN`; one that spans as
    much already, and a flat one, are left as they are."""
    rng = np.random.default_rng(0)
    squeezed = rng.integers(100, 141, (60, 80)).astype(np.uint8)
    out = with_contrast(squeezed)
    low, high = np.percentile(out, (0.5, 99.5))
    assert high - low == pytest.approx(MIN_SPAN, abs=3.0)
    assert np.median(out) == pytest.approx(np.median(squeezed), abs=2.0)
    wide = rng.integers(40, 221, (60, 80)).astype(np.uint8)
    assert with_contrast(wide) is wide
    flat = np.full((60, 80), 90, dtype=np.uint8)
    assert with_contrast(flat) is flat


def test_on_an_edge_rich_target_a_render_of_another_view_is_no_fit(engine, catalog):
    """Half under a blocky noise texture (gravel or foliage at its worst), the fit from the nadir
    view's render leaves most of its points on the oblique target's edges (0.64 measured), as
    many as a right fit leaves on a plain target: above the chance of the target's edges (0.54),
    not even a quarter."""
    scene = catalog.get("demo")
    (_, truth), (_, elsewhere) = VIEWS[0], VIEWS[1]
    plain = gray(rendered(engine, scene, truth)[0])
    rgb, depth, camera = rendered(engine, scene, elsewhere)
    fit = refine_dense(textured(plain, 0.5, seed=1), rgb, depth, camera, fit_focal=False)
    assert fit.chance > 0.3
    assert fit.inliers >= MIN_INLIER_SHARE * fit.points  # what used to converge
    assert above_chance(fit.inliers, fit.points, fit.chance) < 0.3
    assert refine_dense(plain, rgb, depth, camera, fit_focal=False).chance < 0.05


def levels_made(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The scales of the target's distance-map levels made from now on."""
    import services.optimizer.free.target_maps as target_maps

    made: list[int] = []
    level = target_maps.target_level

    def counted(*args, **kwargs):
        made.append(args[1])
        return level(*args, **kwargs)

    monkeypatch.setattr(target_maps, "target_level", counted)
    return made


def test_a_start_already_on_the_targets_edges_skips_the_coarse_levels(engine, catalog, monkeypatch):
    """A start 0.1 % and 0.1° off leaves nearly every edge point on the target's: its pose is
    fitted at full resolution only (one level's distance maps), and still lands on the truth;
    with the focal length fitted every level runs."""
    import services.optimizer.free.dense as dense

    made = levels_made(monkeypatch)
    scene = catalog.get("demo")
    truth = VIEWS[0][1]
    target, _, _ = rendered(engine, scene, truth)
    start = moved(truth, 0.1, 0.001 * scene.spec.camera.radius, seed=4, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=False)
    assert fit.start_inliers >= dense.FINE_START_SHARE * fit.points
    assert made == [1]
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert distance < 0.003 * scene.spec.camera.radius
    assert angle < 0.1
    made.clear()
    refine_dense(gray(target), rgb, depth, camera, fit_focal=True)
    assert sorted(made) == [1, 2, 4]


def test_the_focal_length_is_refined_when_not_given(engine, catalog):
    """The rolled view, started 8 % wide in fov and 2 %/2° off."""
    scene = catalog.get("garden")
    _, truth = VIEWS[2]
    target, _, true_camera = rendered(engine, scene, truth)
    start = moved(truth, 2.0, 0.02 * scene.spec.camera.radius, seed=4, fov_deg=54.0)
    rgb, depth, camera = rendered(engine, scene, start)
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=True)
    assert fit.intrinsics.fx == pytest.approx(true_camera.fx, rel=0.01)
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert distance < 0.01 * scene.spec.camera.radius
    assert angle < 0.5


def test_the_pyramid_of_an_enlarged_film_keeps_its_tolerances_in_the_target_s_pixels():
    assert pyramid(1.0) == LEVELS
    # on a film twice the target's: coarse levels of as many target pixels, the finest the
    # film's own with σ and τ of as many target pixels
    assert pyramid(2.0) == ((8, 2.0, 8.0), (4, 1.5, 6.0), (1, 2.0, 10.0))


def test_a_small_target_enlarged_twice_is_refined_on_the_enlarged_film(engine, catalog):
    """The rolled view's target at 320 x 240, its grey enlarged to a 640 x 480 render started
    8 % wide in fov and 2 %/2° off: the focal length comes back in the film's pixels."""
    scene = catalog.get("garden")
    _, truth = VIEWS[2]
    target, _, true_camera = rendered(engine, scene, truth)
    enlarged = cv2.resize(gray(target), (2 * W, 2 * H), interpolation=cv2.INTER_CUBIC)
    start = moved(truth, 2.0, 0.02 * scene.spec.camera.radius, seed=4, fov_deg=54.0)
    view = resolve_free_camera(scene, start, 2 * W, 2 * H)
    rgb = engine.render(scene, view, 2 * W, 2 * H, SPP, 0).rgb
    depth = engine.depth(scene, view, 2 * W, 2 * H).depth
    fit = refine_dense(enlarged, rgb, depth, view.camera, fit_focal=True, pixel=2.0)
    assert fit.intrinsics.fx == pytest.approx(2.0 * true_camera.fx, rel=0.01)
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert distance < 0.01 * scene.spec.camera.radius
    assert angle < 0.5
    assert fit.share() > 0.8  # explained within two of the target's pixels, not the film's


@pytest.mark.parametrize(("scene_id", "truth"), VIEWS, ids=["oblique", "nadir", "rolled"])
def test_dense_refinement_beats_the_box_only_fit_on_the_same_target(
    engine, catalog, scene_id, truth
):
    """The issue's "done when": the box solver on the target's rendered boxes with the
    detector's edge noise (0.7 px at 320 wide), then one render at its answer and the dense
    refinement: the dense pose is closer in position and rotation."""
    scene = catalog.get(scene_id)
    objects = scene_objects(scene.spec, scene.assets)
    annotations, detections = noisy_boxes(engine, scene, objects, truth, seed=7)
    true = annotations.camera
    intrinsics = Intrinsics(true.fx, true.fy, true.cx, true.cy)
    answer = solve_free_pose(objects, detections, W, H, intrinsics)
    assert answer.pose is not None
    box_errors = errors(answer.pose.rotation(), answer.pose.position, truth)
    target, _, _ = rendered(engine, scene, truth)
    rgb, depth, camera = rendered(engine, scene, answer.pose.free_camera())
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=False)
    dense_errors = errors(fit.rotation.T, fit.position, truth)
    assert dense_errors[0] < box_errors[0]
    assert dense_errors[1] < box_errors[1]
    assert dense_errors[0] < 0.02 * scene.spec.camera.radius  # the 2 %


def test_a_render_without_edges_keeps_the_start_pose(catalog):
    """Nothing to align (a blank render): the start comes back, with no point used."""
    camera = free_pinhole_camera(VIEWS[0][1], W, H, 45.0)
    blank = np.full((H, W, 3), 128, np.uint8)
    fit = refine_dense(
        blank[..., 0], blank, np.full((H, W), 5.0, np.float32), camera, fit_focal=True
    )
    assert fit.points == 0
    assert np.allclose(fit.translation, camera.translation)
    assert fit.intrinsics.fx == pytest.approx(camera.fx)


def test_images_of_another_film_are_refused():
    camera = free_pinhole_camera(VIEWS[0][1], W, H, 45.0)
    with pytest.raises(ValueError, match="film"):
        refine_dense(
            np.zeros((H // 2, W // 2), np.uint8),
            np.zeros((H, W, 3), np.uint8),
            np.zeros((H, W), np.float32),
            camera,
            fit_focal=False,
        )


def _fov_error(fx: float, true_fx: float) -> float:
    """Relative fov error of focal length ``fx`` against ``true_fx`` on the W-wide film."""
    fov, true = (2.0 * math.atan(W / (2.0 * f)) for f in (fx, true_fx))
    return abs(fov - true) / true


# (scene, true camera) seen from above with a fov unlike the scene camera's: the box solver's
# focal is several percent off there (the valley of distance against focal length).
STEEP = [
    ("demo", FreeCamera(position=(4.0, -3.0, 6.0), look_at=(0.3, 0.2, 0.0), fov_deg=52.0)),
    ("garden", FreeCamera(position=(2.0, 3.0, 7.0), look_at=(0.0, 0.5, 0.0), fov_deg=36.0)),
]


@pytest.mark.parametrize(("scene_id", "truth"), STEEP, ids=["demo-oblique", "garden-steep"])
def test_an_unknown_fov_is_found_from_the_box_solvers_answer(engine, catalog, scene_id, truth):
    """fov not given: the box solver's answer (its focal estimated from the boxes), one render
    there and the dense fit with the focal free, and one render more when that fit moved far
    (:func:`worth_another_render`), as the search does: the pose within 2 % of the radius and 1°
    (the issue's goal) and the fov within 2 %, both closer than the box solver's. The fov's
    goal is a median (≤ 1 %), which the free bench measures: along the dolly-zoom valley one
    case lands anywhere within about a percent (garden-steep 0.6 % with LSMR steps, 1.4 % with
    exact ones, whose bench medians were the lower of the two on seed 2)."""
    scene = catalog.get(scene_id)
    radius = scene.spec.camera.radius
    objects = scene_objects(scene.spec, scene.assets)
    annotations, detections = noisy_boxes(engine, scene, objects, truth, seed=5)
    answer = solve_free_pose(objects, detections, W, H)
    assert answer.pose is not None
    true_fx = annotations.camera.fx
    box_fov = _fov_error(answer.pose.intrinsics.fx_px, true_fx)
    target, _, _ = rendered(engine, scene, truth)
    rgb, depth, camera = rendered(engine, scene, answer.pose.free_camera())
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=True)
    renders = 1
    if worth_another_render(fit, camera):
        moved_to = fit.camera(camera)
        again = FreeCamera(
            position=moved_to.position,
            quaternion_wxyz=quaternion_of_rotation(np.asarray(moved_to.rotation).T),
            fx_px=moved_to.fx,
            fy_px=moved_to.fy,
            cx_px=moved_to.cx,
            cy_px=moved_to.cy,
        )
        rgb, depth, camera = rendered(engine, scene, again)
        fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=True)
        renders += 1
    fov = _fov_error(fit.intrinsics.fx, true_fx)
    distance, angle = errors(fit.rotation.T, fit.position, truth)
    assert fit.focal_fitted
    assert fov < 0.02
    assert fov < box_fov
    assert distance < 0.02 * radius
    assert angle < 1.0


def _synthetic_problem(fit_focal: bool, distortion=None, limit=None, fit_radial=False):
    """A pyramid level of a random edge image and random points in front of the camera."""
    from services.optimizer.free import edges

    rng = np.random.default_rng(3)
    image = (rng.random((H, W)) > 0.97).astype(np.uint8) * 255
    level = edges.target_level(cv2.GaussianBlur(image, (0, 0), 2.0), 1, 1.0, 5.0)
    world = rng.normal(size=(400, 3)) + [0.0, 0.0, 8.0]
    points = edges.EdgePoints(world=world, bins=rng.integers(0, 8, 400))
    k = Intrinsics(300.0, 300.0, W / 2, H / 2)
    return ChamferProblem(points, level, k, distortion, fit_focal, limit, fit_radial)


@pytest.mark.parametrize("fit_focal", [False, True])
def test_the_pinhole_jacobian_is_opencvs(fit_focal):
    problem = _synthetic_problem(fit_focal)
    x = np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.5, 1.1][: 7 if fit_focal else 6])
    problem._project(x)
    ours = problem._pinhole_columns(x)
    fx, fy = problem._focal(x)
    matrix = np.array([[fx, 0.0, W / 2], [0.0, fy, H / 2], [0.0, 0.0, 1.0]])
    uv, jacobian = cv2.projectPoints(problem.world, x[:3], x[3:6], matrix, np.zeros(4))
    np.testing.assert_allclose(problem._uv, uv.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(ours, problem._opencv_columns(jacobian, fx, fy, x), atol=1e-9)


@pytest.mark.parametrize("fit_focal", [True, False], ids=["with-zoom", "pose-only"])
def test_the_radial_terms_jacobian_is_the_projections_derivative(fit_focal):
    """The lens check's ``k1`` column (and the pose's, and the zoom's, beside it) against
    central differences of the projected pixels."""
    problem = _synthetic_problem(fit_focal=fit_focal, fit_radial=True)
    x = np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.5, 1.1, -0.15][: 8 if fit_focal else 7])
    x[-1] = -0.15
    problem._project(x)
    columns = problem._columns
    assert columns is not None
    assert columns.shape == (400, 2, x.size)
    for i in range(x.size):
        step = np.zeros(x.size)
        step[i] = 1e-6
        ahead = problem._project(x + step)[0].copy()
        behind = problem._project(x - step)[0].copy()
        np.testing.assert_allclose(columns[:, :, i], (ahead - behind) / 2e-6, rtol=1e-4, atol=1e-4)


def test_a_radial_term_is_fitted_on_a_pinhole_lens_only():
    from services.common.geometry.free_camera import LensDistortion

    with pytest.raises(ValueError, match="radial"):
        _synthetic_problem(fit_focal=True, distortion=LensDistortion(k1=-0.1), fit_radial=True)


def test_the_jacobian_reuses_the_residuals_projection(monkeypatch):
    from services.optimizer.free import dense

    problem = _synthetic_problem(fit_focal=True)
    x = np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.5, 1.1])
    problem.residuals(x)
    calls = []
    rodrigues = dense.cv2.Rodrigues
    monkeypatch.setattr(dense.cv2, "Rodrigues", lambda v: calls.append(1) or rodrigues(v))
    problem.jacobian(x.copy())  # the same pose: only the rotation's derivative is asked for
    assert len(calls) == 1
    problem.residuals(x + 1e-3)
    assert len(calls) == 2


def test_a_level_fits_at_most_its_share_of_the_points():
    assert len(_synthetic_problem(False, limit=100).world) == 100
    assert len(_synthetic_problem(False, limit=None).world) == 400


def all_edges_and_outline(engine, scene, lighting, truth: FreeCamera):
    """The target is ``truth`` rendered in ``lighting`` (the scene or a copy lit otherwise), the
    start 2 %/2° off; the errors (distance, degrees) of the fits on all the render's edges and
    on its outline."""
    radius = scene.spec.camera.radius
    target, _, _ = rendered(engine, lighting, truth)
    start = moved(truth, 2.0, 0.02 * radius, seed=5, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    geometry = engine.depth(scene, resolve_free_camera(scene, start, W, H), W, H)
    near = outline(geometry.depth, geometry.objects, geometry.shading)
    fits = [
        refine_dense(gray(target), rgb, depth, camera, fit_focal=False, near=n)
        for n in (None, near)
    ]
    return [errors(f.rotation.T, f.position, truth) for f in fits]


@pytest.mark.parametrize(("scene_id", "truth"), VIEWS, ids=["oblique", "nadir", "rolled"])
def test_a_target_under_another_light_is_refined_on_the_outline(
    engine, catalog, tmp_path, scene_id, truth
):
    """The target is the scene under a light turned and tilted away (the bench's ``photo``
    copy), its shadows elsewhere; the start is 2 %/2° off. On the render's outline (no shadows
    of the scene file's light) the fit ends within 1 % and 0.5°, or a quarter closer than on all
    the render's edges: measured first, 0.25 %/0.25° against 2.2 %/1.9° (oblique), 0.07 %/0.02°
    both (rolled), and on the nadir view of five equal balls, whose shadows merge with their
    outlines, 12.6 %/6.7° against 25.8 %/14.2° (a fit the controller then refuses: below 75 %
    of the points on the target's edges)."""
    scene = catalog.get(scene_id)
    copy = alter_scene(scene, "photo", np.random.default_rng(6), tmp_path, f"{scene_id}_lit")
    lit = SceneCatalog([tmp_path]).get(copy.id)
    (plain, plain_angle), (distance, angle) = all_edges_and_outline(engine, scene, lit, truth)
    assert distance <= max(0.75 * plain, 0.01 * scene.spec.camera.radius)
    assert angle <= max(0.75 * plain_angle, 0.5)


@pytest.mark.parametrize(("scene_id", "truth"), VIEWS, ids=["oblique", "nadir", "rolled"])
def test_under_the_renders_own_light_its_shadows_join_the_fit(engine, catalog, scene_id, truth):
    """The target under the scene file's own light, the start 2 %/2° off: the shadows agree, so
    they join a last fit (``LIGHT_SHARE``), and the fit is as close as on all the render's edges
    (within 0.4 % and 0.2° or better). Measured first on the nadir view of five balls: 0.24 %/
    0.11° (all edges 0.30 %/0.14°; the outline alone 0.56 %/0.34°)."""
    scene = catalog.get(scene_id)
    (plain, plain_angle), (distance, angle) = all_edges_and_outline(engine, scene, scene, truth)
    assert distance <= max(plain, 0.004 * scene.spec.camera.radius)
    assert angle <= max(plain_angle, 0.2)


def test_a_focal_length_past_its_bounds_is_not_kept(engine, catalog):
    """The rolled view, started 8 % wide, with a scene camera whose focal length puts the
    bound of FOCAL_BOUNDS halfway between the start's and the true one: the fit ends past the
    bound, and keeps the start's focal length (the pose alone fitted). Given a scene camera
    of the start's focal length, whose bounds reach past the truth, the same fit finds it."""
    scene = catalog.get("garden")
    _, truth = VIEWS[2]
    target, _, true_camera = rendered(engine, scene, truth)
    start = moved(truth, 2.0, 0.02 * scene.spec.camera.radius, seed=4, fov_deg=54.0)
    rgb, depth, camera = rendered(engine, scene, start)
    assert camera.fx < 0.95 * true_camera.fx
    halfway = (camera.fx + true_camera.fx) / 2.0 / FOCAL_BOUNDS[1]
    bounded = refine_dense(
        gray(target), rgb, depth, camera, fit_focal=True, focal_range=FocalRange.about(halfway)
    )
    assert not bounded.focal_fitted
    assert bounded.intrinsics.fx == pytest.approx(camera.fx)
    lenses = FocalRange.about(camera.fx)
    free = refine_dense(gray(target), rgb, depth, camera, fit_focal=True, focal_range=lenses)
    assert free.focal_fitted
    assert free.intrinsics.fx == pytest.approx(true_camera.fx, rel=0.01)


@pytest.mark.parametrize("fit_focal", [True, False], ids=["fov-fitted", "fov-given"])
def test_the_lens_check_sees_a_distorted_photos_bend_and_not_a_pinholes(engine, catalog, fit_focal):
    """The oblique view through a 65° lens, as a pinhole and with barrel distortion (``k1``
    −0.15), each fitted from one pinhole render 1 %/1° off (its fov 67°, fitted or taken as
    given) with the lens check: the distorted photo's ``k1`` is found near its own and bends
    beyond the thresholds (measured first, fov fitted: −0.164 ± 0.008, 6.9 px), the pinhole's
    stays near 0 and below them (4·10⁻⁶)."""
    from services.common.geometry.free_camera import LensDistortion
    from services.optimizer.lens_pose import BEND_PX, BEND_Z, lens_explains

    scene_id, oblique = VIEWS[0]
    scene = catalog.get(scene_id)
    truth = oblique.model_copy(update={"fov_deg": 65.0})
    start = moved(truth, 1.0, 0.01 * scene.spec.camera.radius, seed=3, fov_deg=67.0)
    rgb, depth, camera = rendered(engine, scene, start)
    checks = {}
    for name, lens in (("pinhole", None), ("barrel", LensDistortion(k1=-0.15))):
        target, _, _ = rendered(engine, scene, truth.model_copy(update={"distortion": lens}))
        fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=fit_focal, check_radial=True)
        assert fit.radial is not None
        checks[name] = fit.radial
    barrel, pinhole = checks["barrel"], checks["pinhole"]
    assert -0.2 < barrel.k1 < -0.1
    assert barrel.bend_px >= BEND_PX
    assert abs(barrel.k1) >= BEND_Z * barrel.sigma
    assert not barrel.bounded
    assert abs(pinhole.k1) < 0.03
    assert pinhole.bend_px < BEND_PX
    assert lens_explains(barrel)  # measured first: it removes 44 % (fov fitted), 42 % (given)


def test_a_moved_lights_shadows_can_bend_the_check_yet_explain_little(engine, catalog, tmp_path):
    """A pinhole target of the oblique view under a light turned away (the bench's ``photo``
    copy, seed 3), fitted with its fov from a render 1 %/1° off: the shadows' edges pull the
    check's ``k1`` past the bend's thresholds (measured first: −0.11 at 5.2 σ, 2.8 px), yet it
    removes a fraction of a percent of the pinhole fit's robust cost (0.3 %), below
    :data:`LENS_POSE_DROP`: the answer keeps the pinhole's pose. The barrel photo of the test
    above removes 42–44 %."""
    from services.optimizer.lens_pose import LENS_POSE_DROP, lens_explains

    scene_id, truth = VIEWS[0]
    scene = catalog.get(scene_id)
    copy = alter_scene(scene, "photo", np.random.default_rng(3), tmp_path, f"{scene_id}_lit")
    lit = SceneCatalog([tmp_path]).get(copy.id)
    target, _, _ = rendered(engine, lit, truth)
    start = moved(truth, 1.0, 0.01 * scene.spec.camera.radius, seed=3, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    fit = refine_dense(gray(target), rgb, depth, camera, fit_focal=False, check_radial=True)
    check = fit.radial
    assert check is not None
    assert check.cost_drop is not None
    assert abs(check.k1) > 0.05  # the shadows bend it
    assert check.cost_drop < LENS_POSE_DROP
    assert not lens_explains(check)


def test_the_lens_check_is_made_when_asked_and_no_full_lens_is_given(engine, catalog):
    """Asked for, the check is made without a lens or with a radial ``k1`` alone (one an earlier
    check estimated), not with any other lens."""
    from services.common.geometry.free_camera import LensDistortion

    scene_id, truth = VIEWS[0]
    scene = catalog.get(scene_id)
    target, _, _ = rendered(engine, scene, truth)
    start = moved(truth, 1.0, 0.01 * scene.spec.camera.radius, seed=3, fov_deg=truth.fov_deg)
    rgb, depth, camera = rendered(engine, scene, start)
    assert refine_dense(gray(target), rgb, depth, camera, fit_focal=True).radial is None
    for lens, checked in ((LensDistortion(k1=-0.05, k2=0.01), False), (LensDistortion(), True)):
        fit = refine_dense(
            gray(target), rgb, depth, camera, fit_focal=False, distortion=lens, check_radial=True
        )
        assert (fit.radial is not None) == checked


def test_a_lens_the_check_estimated_is_fitted_again_through_its_own_render(engine, catalog):
    """The oblique view at 75° through a lens of two radial terms (``k1`` −0.08, ``k2`` 0.03),
    fitted from a pinhole render 1 %/1° off with the lens check, then rendered again at the
    check's pose through the ``k1`` it estimated and fitted from there, that lens given and
    checked again: the second pose is nearer the truth (measured first: 3.65 %/0.60° → 2.07
    %/0.17°, ``k1`` −0.072 both times). Not every view gains so much (``benchmarks.drone_lens``
    measures the share through the stack)."""
    from services.common.geometry.free_camera import LensDistortion, quaternion_of_rotation

    scene_id, oblique = VIEWS[0]
    scene = catalog.get(scene_id)
    radius = scene.spec.camera.radius
    lens = LensDistortion(k1=-0.08, k2=0.03)
    truth = oblique.model_copy(update={"fov_deg": 75.0, "distortion": lens})
    target, _, _ = rendered(engine, scene, truth)
    start = moved(truth, 1.0, 0.01 * radius, seed=3, fov_deg=78.0)
    rgb, depth, camera = rendered(engine, scene, start)
    first = refine_dense(gray(target), rgb, depth, camera, fit_focal=True, check_radial=True)
    assert first.radial is not None
    estimate = LensDistortion(k1=first.radial.k1)
    fx = camera.fx * first.radial.zoom
    again = FreeCamera(
        position=tuple(float(v) for v in first.radial.position),
        quaternion_wxyz=quaternion_of_rotation(first.radial.rotation.T),
        fov_deg=math.degrees(2.0 * math.atan(camera.width / 2.0 / fx)),
        distortion=estimate,
    )
    rgb, depth, camera = rendered(engine, scene, again)
    second = refine_dense(
        gray(target), rgb, depth, camera, fit_focal=True, distortion=estimate, check_radial=True
    )
    assert second.radial is not None

    def error(check):
        rotation = check.rotation @ truth.rotation()
        turn = math.degrees(math.acos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
        return np.linalg.norm(check.position - np.asarray(truth.position)) / radius, turn

    (position1, turn1), (position2, turn2) = error(first.radial), error(second.radial)
    assert position2 <= 0.75 * position1
    assert turn2 <= turn1
    assert abs(second.radial.k1 - lens.k1) < 0.05
    assert first.radial.cost_drop is not None
    assert second.radial.cost_drop is None  # started through a lens: no pinhole fit to compare
