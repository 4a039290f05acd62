"""Free targets (issue 23, item 5): the drawing keeps every constraint over real annotation
renders at a small film, the metrics are right on known poses, the baseline recovers an exact
pose from exact centroids, and the box-only fit returns the truth without noise."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cosmos.bench.free_targets import (
    BANDS,
    DrawError,
    Estimate,
    FreeTarget,
    LocalRenderer,
    PoseError,
    baseline,
    baseline_pnp,
    box_fit,
    box_only_bound,
    draw_targets,
    evaluate,
    pose_error,
    project_boxes,
    scene_shapes,
    summarize,
    text_table,
)
from cosmos.bench.free_targets.dense import dense_method
from cosmos.bench.free_targets.draw import (
    DISTANCE_RANGE,
    ELEVATION_RANGE_DEG,
    FOV_SPREAD,
    FREE_VARIANTS,
    MIN_OBJECTS,
    MIN_VISIBLE,
    NADIR_SHARE,
    ROLL_LIMIT_DEG,
    band_of,
    elevation_strata,
    target_film,
)
from cosmos.bench.free_targets.estimate import intrinsics_matrix
from cosmos.bench.free_targets.metrics import MISSED
from cosmos.bench.free_targets.report import TargetResult, dense_line, solver_table
from cosmos.bench.free_targets.solver import SOLVER, answer_estimate, confirmed_wrong
from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.depth_archive import DepthImage
from services.common.geometry.free_camera import (
    FreeCamera,
    free_pinhole_camera,
    quaternion_of_rotation,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.scene import LoadedScene
from services.optimizer.free import (
    FreePoseAnswer,
    IntrinsicsUsed,
    PoseCandidate,
    Status,
    scene_objects,
)
from services.renderer.engine import RenderEngine

COUNT, SEED = 7, 3
FILM = (96, 72)


@pytest.fixture(scope="module")
def renderer(engine: RenderEngine, catalog: SceneCatalog) -> Iterator[LocalRenderer]:
    with LocalRenderer(catalog, engine=engine) as local:
        yield local


@pytest.fixture(scope="module")
def garden(catalog: SceneCatalog) -> LoadedScene:
    return catalog.get("garden")


@pytest.fixture(scope="module")
def targets(renderer: LocalRenderer, garden: LoadedScene) -> list[FreeTarget]:
    width, height = FILM
    shapes = scene_shapes(garden)
    return draw_targets(renderer, garden, shapes, COUNT, SEED, width=width, height=height, spp=1)


def test_drawn_cameras_keep_every_constraint(targets: list[FreeTarget], garden: LoadedScene):
    spec = garden.spec.camera
    shapes = scene_shapes(garden)
    assert [t.index for t in targets] == list(range(COUNT))
    for target in targets:
        drawn, camera = target.drawn, target.camera
        position = np.asarray(camera.position)
        distance = float(np.linalg.norm(position - drawn.look_at))
        assert distance == pytest.approx(drawn.distance)
        assert DISTANCE_RANGE[0] * spec.radius <= distance <= DISTANCE_RANGE[1] * spec.radius
        assert 10.0 <= drawn.elevation_deg <= 90.0
        assert drawn.look_at[2] == 0.0
        # it looks at the point, pitched by the elevation, rolled within ±25°
        forward = camera.rotation()[:, 2]
        assert forward == pytest.approx((np.asarray(drawn.look_at) - position) / distance)
        yaw, pitch, roll = yaw_pitch_roll_of_rotation(camera.rotation())
        assert pitch == pytest.approx(drawn.elevation_deg, abs=1e-6)
        if drawn.elevation_deg < 90.0:  # at the nadir, roll and yaw turn about the same axis
            assert roll == pytest.approx(camera.roll_deg, abs=1e-6)
            assert (yaw - camera.yaw_deg + 180.0) % 360.0 == pytest.approx(180.0, abs=1e-6)
        assert abs(camera.roll_deg) <= ROLL_LIMIT_DEG
        assert camera.fov_deg is not None
        assert abs(camera.fov_deg / spec.fov_deg - 1.0) <= FOV_SPREAD
        # above the ground, outside every object
        assert position[2] > 0.0
        assert not np.any(np.all((position > shapes.lo) & (position < shapes.hi), axis=1))
        # at least three objects at least 60 % visible, by the renderer's count
        assert len(target.usable) >= MIN_OBJECTS
        seen = {o.name: o.visible_fraction for o in target.annotations.objects}
        assert all(seen[name] >= MIN_VISIBLE for name in target.usable)
        assert target.annotations.camera.width == FILM[0]
        assert target.png.startswith(b"\x89PNG")
    nadir = [t for t in targets if t.band == "nadir"]
    assert len(nadir) == round(NADIR_SHARE * COUNT)
    assert all(t.drawn.elevation_deg == 90.0 for t in nadir)
    assert sum(not t.intrinsics_given for t in targets) == round(COUNT / 3)


def test_a_fov_range_widens_the_lenses_drawn(renderer: LocalRenderer, garden: LoadedScene):
    width, height = FILM
    shapes, spec = scene_shapes(garden), garden.spec.camera
    wide = draw_targets(
        renderer, garden, shapes, 3, SEED, width=width, height=height, spp=1,
        fov_range=(1.5, 1.6),
    )  # fmt: skip
    for target in wide:
        assert target.camera.fov_deg is not None
        assert 1.5 <= target.camera.fov_deg / spec.fov_deg <= 1.6
        assert target.annotations.camera.fov_deg == pytest.approx(target.camera.fov_deg)
    with pytest.raises(DrawError, match="leaves"):  # a pinhole's fov stays below 170°
        draw_targets(renderer, garden, shapes, 1, SEED, fov_range=(1.0, 170.0 / spec.fov_deg))


def test_a_roll_limit_rolls_the_same_cameras_further(
    renderer: LocalRenderer, garden: LoadedScene, targets: list[FreeTarget]
):
    width, height = FILM
    shapes = scene_shapes(garden)
    upright = draw_targets(
        renderer, garden, shapes, COUNT, SEED, width=width, height=height, spp=1,
        roll_limit=90.0,
    )  # fmt: skip
    same = 0
    for target in upright:
        assert abs(target.camera.roll_deg) <= 90.0
        drawn = targets[target.index].camera
        if target.camera.position == drawn.position:  # not drawn again: the same camera
            same += 1
            assert target.camera.roll_deg == pytest.approx(drawn.roll_deg * 90.0 / 25.0)
            assert target.camera.yaw_deg == drawn.yaw_deg
            assert target.camera.pitch_deg == drawn.pitch_deg
    assert same >= COUNT // 2
    assert max(abs(t.camera.roll_deg) for t in upright) > 25.0


def test_drawing_is_seeded(renderer: LocalRenderer, garden: LoadedScene, targets):
    shapes = scene_shapes(garden)
    width, height = FILM
    picked = [1, 4]
    again = draw_targets(
        renderer, garden, shapes, COUNT, SEED, width=width, height=height, spp=1, only=picked
    )
    assert [t.index for t in again] == picked
    for target in again:
        assert target.camera == targets[target.index].camera
    other = draw_targets(
        renderer, garden, shapes, COUNT, SEED + 1, width=width, height=height, spp=1, only=[1]
    )
    assert other[0].camera != targets[1].camera


def test_elevations_are_stratified_per_intrinsics_group(targets: list[FreeTarget]) -> None:
    """The targets that give their intrinsics take one slice of the elevation range each, and so
    do those that do not: a draw of a few targets spans the range, whatever the seed."""
    nadir = np.array([True, False, False, False, False, False, False, False])
    not_given = np.array([False, True, False, True, False, False, True, False])
    for seed in range(5):
        strata = elevation_strata(nadir, not_given, np.random.default_rng(seed))
        assert strata[0] is None
        for group, size in ((False, 4), (True, 3)):
            members = [
                s for s, n, g in zip(strata, nadir, not_given, strict=True) if not n and g == group
            ]
            assert sorted(j for j, _ in members) == list(range(size))
            assert {m for _, m in members} == {size}
    # the drawn targets: each group's elevations lie in distinct slices of equal width
    lo, hi = ELEVATION_RANGE_DEG
    for group in (True, False):
        elevations = [
            t.drawn.elevation_deg
            for t in targets
            if t.intrinsics_given == group and t.band != "nadir"
        ]
        slices = [int((e - lo) / (hi - lo) * len(elevations)) for e in elevations]
        assert sorted(slices) == list(range(len(elevations)))
    given = [t for t in targets if t.intrinsics_given and t.band != "nadir"]
    assert len(given) >= 3  # the top one of three or more slices starts above 62.7°
    assert "60-89" in {t.band for t in given}


def test_a_scene_that_cannot_be_satisfied_says_so(renderer: LocalRenderer, garden: LoadedScene):
    calls = []

    class Blind:
        def render_png(self, request: RenderRequest) -> bytes:
            raise AssertionError("no target should be rendered")

        def annotations(self, request: RenderRequest) -> RenderAnnotations:
            calls.append(request)
            truth = renderer.annotations(request)
            hidden = tuple(o.model_copy(update={"visible_fraction": 0.3}) for o in truth.objects)
            return truth.model_copy(update={"objects": hidden})

    with pytest.raises(DrawError, match="none of 4 cameras drawn for target 0 sees 3 objects"):
        draw_targets(Blind(), garden, scene_shapes(garden), 2, SEED, width=48, spp=1, max_tries=4)
    assert 1 <= len(calls) <= 4


def test_projected_hulls_match_the_renderers_boxes(targets: list[FreeTarget], garden):
    """The hull points are the rendered objects: their boxes agree with the renderer's, which
    count the pixels whose centre the object covers, to within 1.5 px."""
    shapes = scene_shapes(garden)
    for target in targets:
        camera = target.annotations.camera
        boxes = project_boxes(
            shapes,
            np.asarray(camera.rotation),
            np.asarray(camera.translation),
            intrinsics_matrix(camera),
            (camera.width, camera.height),
        )
        for obj in target.annotations.objects:
            if obj.full_box is not None and obj.name in target.usable:
                i = shapes.names.index(obj.name)
                assert boxes[i] == pytest.approx(obj.full_box, abs=1.5)


def test_bands() -> None:
    assert [band_of(e) for e in (10.0, 29.9, 30.0, 59.9, 60.0, 89.99, 90.0)] == [
        "10-30",
        "10-30",
        "30-60",
        "30-60",
        "60-89",
        "60-89",
        "nadir",
    ]
    assert set(BANDS) == {"10-30", "30-60", "60-89", "nadir"}


CAMERA = FreeCamera(position=(4.0, -3.0, 5.0), look_at=(0.3, 0.2, 0.0), roll_deg=12.0, fov_deg=50)


def _truth() -> Estimate:
    return Estimate.of_camera(CAMERA, 45.0, 320)


def test_metrics_on_known_poses() -> None:
    truth = _truth()
    error = pose_error(truth, truth, 8.0)
    assert (error.position, error.rotation_deg, error.fov_pct) == pytest.approx((0, 0, 0), abs=1e-6)
    turn = Rotation.from_rotvec(np.radians(3.0) * np.array([1.0, 2.0, 2.0]) / 3.0).as_matrix()
    moved = Estimate(turn @ truth.rotation, truth.position + [0.16, 0.0, 0.0], 55.0)
    error = pose_error(moved, truth, 8.0)
    assert error.rotation_deg == pytest.approx(3.0)
    assert error.position == pytest.approx(0.02)
    assert error.fov_pct == pytest.approx(10.0)
    assert pose_error(None, truth, 8.0) is MISSED


def test_summary_shares_and_quantiles() -> None:
    errors = [PoseError(0.01, 0.5, 0.0), PoseError(0.04, 1.5, 0.0), PoseError(0.08, 4.0, 0.0)]
    errors.append(MISSED)
    s = summarize(errors)
    assert s.within == (0.25, 0.5, 0.75)
    assert s.count == 4
    assert s.missed == 1
    assert s.position_median == pytest.approx(0.06)
    assert s.rotation_median_deg == pytest.approx(2.75)
    assert math.isinf(s.position_p95)


def test_baseline_recovers_an_exact_pose_from_exact_centroids(garden: LoadedScene) -> None:
    truth = _truth()
    camera = free_pinhole_camera(CAMERA, 320, 240, 45.0)
    centroids = scene_shapes(garden).centroids
    rotation, translation = truth.world_to_camera
    cam = centroids @ rotation.T + translation
    K = intrinsics_matrix(camera)
    pixels = (cam @ K.T)[:, :2] / cam[:, 2:]
    estimate = baseline_pnp(centroids, pixels, K, camera.fov_deg)
    assert estimate is not None
    error = pose_error(estimate, truth, 8.0)
    assert error.position < 1e-6
    assert error.rotation_deg < 1e-5
    assert baseline_pnp(centroids[:2], pixels[:2], K, camera.fov_deg) is None


def test_baseline_answers_no_pose_where_opencv_reports_nan() -> None:
    """Four box centres on one pixel: ``cv2.solvePnPRansac`` says it succeeded, with a NaN
    translation; the baseline gives no pose, which the bench records as a miss."""
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
    same = np.full((4, 2), 10.0)
    ok, _, tvec, _ = cv2.solvePnPRansac(corners, same, K, None)
    assert ok  # what OpenCV says of it
    assert not np.all(np.isfinite(tvec))
    assert baseline_pnp(corners, same, K, 45.0) is None


def test_box_fit_returns_the_truth_without_noise(garden: LoadedScene) -> None:
    truth = _truth()
    shapes = scene_shapes(garden)
    camera = free_pinhole_camera(CAMERA, 320, 240, 45.0)
    K = intrinsics_matrix(camera)
    boxes = project_boxes(shapes, *truth.world_to_camera, K, (320, 240))
    fitted = box_fit(shapes, boxes, K, (320, 240), truth)
    assert pose_error(fitted, truth, 8.0).position < 1e-9
    # from a start a little off, the fit comes back to the truth
    turn = Rotation.from_rotvec(np.radians([0.5, -0.3, 0.4])).as_matrix()
    start = Estimate(turn @ truth.rotation, truth.position + [0.05, -0.04, 0.03], truth.fov_deg)
    error = pose_error(box_fit(shapes, boxes, K, (320, 240), start), truth, 8.0)
    assert error.position < 1e-5
    assert error.rotation_deg < 1e-3


def test_box_fit_with_the_focal_free(garden: LoadedScene) -> None:
    """Fitted too, the focal length comes back from exact boxes; noise costs it more than a known
    focal length, for distance trades against focal length (a dolly zoom)."""
    truth = _truth()
    shapes = scene_shapes(garden)
    camera = free_pinhole_camera(CAMERA, 320, 240, 45.0)
    K = intrinsics_matrix(camera)
    boxes = project_boxes(shapes, *truth.world_to_camera, K, (320, 240))
    # from the truth but told a focal length 10 % long, the fit finds the true one
    long = K.copy()
    long[0, 0] *= 1.1
    long[1, 1] *= 1.1
    wrong = box_fit(shapes, boxes, long, (320, 240), truth)
    assert pose_error(wrong, truth, 8.0).position > 0.01
    fitted = box_fit(shapes, boxes, long, (320, 240), truth, fit_focal=True)
    assert abs(fitted.fov_deg - truth.fov_deg) < 1e-6
    assert pose_error(fitted, truth, 8.0).position < 1e-6
    # under the same edge noise, the focal left free moves the fit farther, on average
    rng = np.random.default_rng(5)
    known, free = [], []
    for _ in range(12):
        noisy = boxes + rng.normal(0.0, 0.7, boxes.shape)
        known.append(pose_error(box_fit(shapes, noisy, K, (320, 240), truth), truth, 8.0))
        free.append(
            pose_error(box_fit(shapes, noisy, K, (320, 240), truth, fit_focal=True), truth, 8.0)
        )
    assert np.mean([e.position for e in free]) > np.mean([e.position for e in known])
    assert all(e.fov_pct == 0.0 for e in known)
    assert all(e.fov_pct > 0.0 for e in free)


def test_references_on_drawn_targets(targets: list[FreeTarget], garden: LoadedScene) -> None:
    shapes = scene_shapes(garden)
    radius = garden.spec.camera.radius
    for target in targets:
        truth = Estimate.of_camera(target.camera, 45.0, FILM[0])
        exact = box_only_bound(target, shapes, np.random.default_rng(0), sigma_px=0.0)
        assert pose_error(exact, truth, radius).position < 1e-6
        noisy = box_only_bound(target, shapes, np.random.default_rng(0))
        assert pose_error(noisy, truth, radius).position < 0.2
        # the bound fits the focal length exactly when the target does not give it
        assert (pose_error(noisy, truth, radius).fov_pct > 0.0) != target.intrinsics_given
    assert any(baseline(t) is not None for t in targets)
    results = evaluate(targets, shapes, radius, SEED)
    table = text_table(results)
    assert "box-only bound" in table
    assert "baseline" in table
    assert SOLVER not in table
    assert table.count("all") == 2
    solved = evaluate(targets, shapes, radius, SEED, scene_objects(garden.spec, garden.assets))
    assert all(r.status in ("found", "ambiguous", "failed") for r in solved)
    solver_rows = [line.split() for line in text_table(solved).splitlines() if SOLVER in line]
    assert solver_rows[-1][3:5] == ["all", str(COUNT)]
    assert solver_table(solved).splitlines()[-1].split()[:3] == ["garden", "all", str(COUNT)]
    by_objects = text_table(results, by="objects").splitlines()
    assert by_objects[0].split()[2] == "objects"
    counts = {str(len(t.usable)) for t in targets}
    assert {line.split()[2] for line in by_objects[1:] if "baseline" in line} == counts | {"all"}


def test_variants_apply_to_free_targets(targets: list[FreeTarget]) -> None:
    rng = np.random.default_rng(0)
    target = targets[0]
    assert target.image("clean", rng) == target.png
    assert target.image("jpeg", rng).startswith(b"\xff\xd8")
    assert target.image("noise", rng) != target.png


def _answer(status: Status, estimate: Estimate) -> FreePoseAnswer:
    """An answer whose best pose is ``estimate``."""
    pose = PoseCandidate(
        position=tuple(float(v) for v in estimate.position),
        quaternion_wxyz=quaternion_of_rotation(estimate.rotation),
        yaw_pitch_roll_deg=yaw_pitch_roll_of_rotation(estimate.rotation),
        intrinsics=IntrinsicsUsed(300.0, 300.0, 160.0, 120.0, estimate.fov_deg, "estimated"),
        residual_px=0.5,
        correspondences=(),
        position_sigma=0.01,
        rotation_sigma_deg=0.1,
    )
    return FreePoseAnswer(status, "", pose, (), 4)


def test_confirmed_wrong_counts_found_answers_far_from_the_truth() -> None:
    truth = _truth()
    right = pose_error(answer_estimate(_answer("found", truth)), truth, 8.0)
    assert (right.position, right.rotation_deg) == pytest.approx((0.0, 0.0), abs=1e-6)
    moved = Estimate(truth.rotation, truth.position + [1.2, 0.0, 0.0], truth.fov_deg)  # 15 % r
    wrong = pose_error(answer_estimate(_answer("found", moved)), truth, 8.0)
    near = Estimate(truth.rotation, truth.position + [0.56, 0.0, 0.0], truth.fov_deg)  # 7 % r
    close = pose_error(answer_estimate(_answer("found", near)), truth, 8.0)
    assert answer_estimate(FreePoseAnswer("failed", "", None, (), 0)) is None
    assert confirmed_wrong([right], ["found"]) == 0
    assert (
        confirmed_wrong([right, wrong, wrong, close], ["found", "found", "ambiguous", "found"]) == 1
    )
    assert confirmed_wrong([close], ["found"], (0.05, 2.0)) == 1
    results = [
        TargetResult("s", i, "nadir", i == 2, 4, {SOLVER: e}, status)
        for i, (e, status) in enumerate([(right, "found"), (wrong, "found"), (MISSED, "failed")])
    ]
    header, nadir, total = (line.split() for line in solver_table(results).splitlines())
    assert nadir == total[:1] + ["nadir"] + total[2:]
    # n, found, ambiguous, failed, wrong >10%/5° (of them no K), found >5%/2°, fov median and n
    # without K
    assert total[2:] == ["3", "67%", "0%", "33%", "1", "1", "1", "0.0", "2"]


def test_the_dense_stage_renders_once_or_twice_per_target_and_reports_every_variant(
    targets: list[FreeTarget], garden: LoadedScene, renderer: LocalRenderer
) -> None:
    shapes = scene_shapes(garden)
    radius = garden.spec.camera.radius
    objects = scene_objects(garden.spec, garden.assets)
    widths: list[int] = []

    class Spy:
        """The renderer, keeping the film width of every depth render."""

        def depth(self, request: RenderRequest) -> DepthImage:
            widths.append(request.width)
            return renderer.depth(request)

        def __getattr__(self, name: str) -> Any:
            return getattr(renderer, name)

    results = evaluate(targets[:3], shapes, radius, SEED, objects, Spy(), spp=1)
    # a target without its intrinsics is refined, as a search refines it, on twice its film
    films = {t.annotations.camera.width * (1 if t.intrinsics_given else 2) for t in targets[:3]}
    assert set(widths) <= films
    assert any(not t.intrinsics_given for t in targets[:3]) == (max(widths) > FILM[0])
    methods = [dense_method(v) for v in FREE_VARIANTS]
    for result in results:
        # A second render only where the focal length was fitted and moved far.
        allowed = {0} if result.status == "failed" else {1} if result.intrinsics_given else {1, 2}
        assert result.renders in allowed
        assert set(methods) <= set(result.errors)
        assert all(result.errors[m].position < math.inf for m in methods)
    table = text_table(results, by="given")
    assert table.splitlines()[0].split()[2] == "intrinsics"
    assert all(any(m in line for line in table.splitlines()) for m in methods)
    assert dense_line(results).startswith("dense: renders per search median 1")


def test_the_targets_film_follows_the_width_and_aspect_asked_for():
    """``--target-width`` alone keeps the scene camera's aspect (height None: the draw's own);
    ``--target-aspect`` sets the height from the width asked for, else the scene camera's."""
    assert target_film(None, None, 320) == (None, None)
    assert target_film(1280, None, 320) == (1280, None)
    assert target_film(None, (16, 9), 320) == (320, 180)
    assert target_film(1280, (4, 3), 320) == (1280, 960)
    assert target_film(1001, (16, 9), 320) == (1001, 563)
