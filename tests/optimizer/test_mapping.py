"""Object mapping against the renderer's ground truth (not against itself), plus metamorphic
and noise checks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.common.geometry.pose import Pose
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import CalibrationStore
from services.optimizer.mapping import clipped_sides, hidden_behind, map_exact, map_paper
from services.optimizer.proxies import kind_of


def annotated_errors(engine, catalog, scene_id: str, step: int):
    """Per class: exact and paper position errors of wholly visible objects over every
    ``step``-th grid pose."""
    scene = catalog.get(scene_id)
    grid = scene.spec.search.grid()
    camera = scene.spec.camera
    calibration = CalibrationStore.load().find(camera)
    errors: dict[str, dict[str, list[float]]] = {}
    reliable: list[bool] = []
    for flat in range(0, grid.size, step):
        index = grid.unflat(flat)
        pose = grid.pose(index)
        ann = engine.annotate(scene, pose, camera.width, camera.height, index)
        objects = [o for o in ann.objects if o.box is not None and o.visible_fraction >= 0.99]
        boxes = np.array([o.box for o in objects])
        truth = np.array([o.position[:2] for o in objects])
        exact = map_exact(boxes, [kind_of(o.shape) for o in objects], camera, *_angles(pose))
        paper = map_paper(boxes, camera, *_angles(pose), calibration)
        reliable.extend(exact.reliable.tolist())
        for obj, e, p in zip(
            objects,
            np.linalg.norm(exact.position - truth, axis=1),
            np.linalg.norm(paper.position - truth, axis=1),
            strict=True,
        ):
            cell = errors.setdefault(obj.shape, {"exact": [], "paper": []})
            cell["exact"].append(float(e))
            cell["paper"].append(float(p) if np.isfinite(p) else np.inf)
    return errors, reliable


def _angles(pose: Pose) -> tuple[float, float]:
    return pose.theta_deg, pose.phi_deg


@pytest.fixture(scope="module")
def demo_errors(engine, catalog):
    return annotated_errors(engine, catalog, "demo", 9)


@pytest.fixture(scope="module")
def garden_errors(engine, catalog):
    return annotated_errors(engine, catalog, "garden", 9)


def test_exact_mapping_places_balls_to_a_centimetre(demo_errors):
    errors, reliable = demo_errors
    exact = np.array(errors["sphere"]["exact"])
    assert len(exact) >= 100
    assert np.median(exact) < 0.015  # balls of radius 0.45, hemisphere radius 8
    assert np.percentile(exact, 95) < 0.06
    assert np.mean(reliable) > 0.9


@pytest.mark.parametrize(
    ("shape", "median", "p95"),
    [("sphere", 0.015, 0.06), ("cube", 0.04, 0.12), ("cylinder", 0.03, 0.12), ("cone", 0.03, 0.1)],
)
def test_exact_mapping_of_every_primitive(garden_errors, shape, median, p95):
    values = np.array(garden_errors[0][shape]["exact"])
    assert len(values) >= 25
    assert np.median(values) < median
    assert np.percentile(values, 95) < p95


def test_meshes_are_mapped_to_within_their_size(garden_errors):
    """A mesh is only a cylinder to the optimizer: its footprint's depth is a guess."""
    values = np.array(garden_errors[0]["mesh"]["exact"])
    assert np.median(values) < 0.3
    assert np.percentile(values, 95) < 0.6


def test_paper_mapping_is_sane_but_worse_than_exact(demo_errors, garden_errors):
    for errors, median in ((demo_errors[0], 0.1), (garden_errors[0], 0.4)):
        paper = np.concatenate([np.array(c["paper"]) for c in errors.values()])
        exact = np.concatenate([np.array(c["exact"]) for c in errors.values()])
        finite = paper[np.isfinite(paper)]
        assert len(finite) >= 0.95 * len(paper)
        assert np.median(finite) < median
        assert np.median(finite) > 2 * np.median(exact)


def test_the_literal_eq4_misplaces_raised_objects(engine, catalog):
    """With rays meeting the ground itself (h = 0) a ball's centre row lands too far away; the
    fitted reference height removes most of that."""
    scene = catalog.get("demo")
    camera = scene.spec.camera
    calibration = CalibrationStore.load().find(camera)
    literal = dataclasses.replace(calibration, reference_height=0.0)
    pose = Pose(theta_deg=60.0, phi_deg=30.0)
    ann = engine.annotate(scene, pose, camera.width, camera.height, None)
    boxes = np.array([o.box for o in ann.objects])
    truth = np.array([o.position[:2] for o in ann.objects])
    fitted = np.linalg.norm(map_paper(boxes, camera, 60.0, 30.0, calibration).position - truth, 1)
    naive = np.linalg.norm(map_paper(boxes, camera, 60.0, 30.0, literal).position - truth, 1)
    assert calibration.reference_height == pytest.approx(0.45, abs=0.05)  # the balls' centres
    assert np.median(naive) > 0.5
    assert np.median(fitted) < 0.2


def test_rotating_the_pose_rotates_the_map():
    """Metamorphic: the same boxes seen from φ + ψ map to positions turned by ψ."""
    camera = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)
    boxes = np.array([[100.0, 80.0, 140.0, 120.0], [200.0, 150.0, 230.0, 200.0]])
    kinds = [kind_of("sphere"), kind_of("cylinder")]
    base = map_exact(boxes, kinds, camera, 40.0, 10.0)
    turned = map_exact(boxes, kinds, camera, 40.0, 10.0 + 75.0)
    a = np.radians(75.0)
    rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    # Exact for the ball; the prism's rims are sampled at fixed world azimuths (32 points), which
    # turning the pose moves relative to the view: millimetres.
    np.testing.assert_allclose(turned.position[0], base.position[0] @ rotation.T, atol=1e-7)
    np.testing.assert_allclose(turned.position, base.position @ rotation.T, atol=5e-3)
    np.testing.assert_allclose(turned.offsets, base.offsets, atol=5e-3)


def test_error_grows_smoothly_with_pixel_noise(engine, catalog):
    scene = catalog.get("demo")
    camera = scene.spec.camera
    pose = Pose(theta_deg=45.0, phi_deg=100.0)
    ann = engine.annotate(scene, pose, camera.width, camera.height, None)
    boxes = np.array([o.box for o in ann.objects])
    truth = np.array([o.position[:2] for o in ann.objects])
    kinds = [kind_of(o.shape) for o in ann.objects]
    rng = np.random.default_rng(7)
    direction = rng.normal(size=(200, *boxes.shape))
    means = []
    for sigma in (0.0, 0.5, 1.0, 2.0, 4.0):
        noisy = np.concatenate(boxes[None] + sigma * direction)
        mapped = map_exact(noisy, kinds * 200, camera, 45.0, 100.0)
        means.append(float(np.mean(np.linalg.norm(mapped.position - np.tile(truth, (200, 1)), 1))))
    assert means == sorted(means)
    assert means[-1] < 10 * means[1] + 0.05  # no blow-up: roughly linear in σ


def test_the_horizon_maps_nothing():
    """From θ = 90° the camera is in the ground plane: scaling the scene about it changes
    nothing in the image, so no distance can be recovered."""
    camera = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)
    mapped = map_exact([[100.0, 100.0, 130.0, 130.0]], [kind_of("sphere")], camera, 90.0, 0.0)
    assert not mapped.reliable.any()
    assert np.isnan(mapped.position).all()


def test_cut_and_hidden_boxes_are_flagged():
    boxes = np.array(
        [[0.0, 10.0, 20.0, 30.0], [50, 50, 90, 90], [60, 40, 100, 80], [5, 5, 319.8, 239.9]]
    )
    cut = clipped_sides(boxes, 320, 240)
    assert cut[0].tolist() == [True, False, False, False]
    assert cut[3].tolist() == [False, False, True, True]
    hidden = hidden_behind(boxes[1:3])
    assert hidden.tolist() == [False, True]  # the box reaching lower is in front
