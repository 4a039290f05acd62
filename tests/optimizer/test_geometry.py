"""Vectorised cameras and proxy boxes: against the project's camera model and dense sampling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services.common.geometry.camera import camera_axes, pinhole_camera, project
from services.common.geometry.pose import Pose
from services.common.geometry.scene import CameraSpec
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer import proxies
from services.optimizer.geometry import PinholeCameras
from services.optimizer.proxies import (
    RIM_POINTS,
    ProxyKind,
    clip_boxes,
    kind_of,
    proxy_boxes,
    sphere_boxes,
)

CAMERA = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)
thetas = st.floats(0.0, 90.0)
phis = st.floats(0.0, 360.0)
points = hnp.arrays(np.float64, (6, 3), elements=st.floats(-3.0, 3.0))


@settings(max_examples=80, deadline=None)
@given(theta=thetas, phi=phis, pts=points)
def test_cameras_project_like_the_shared_camera_model(theta, phi, pts):
    mine, depth = PinholeCameras.at(theta, phi, CAMERA).project(pts)
    model = pinhole_camera(Pose(theta_deg=theta, phi_deg=phi), 8.0, 45.0, 320, 240)
    theirs, their_depth = project(pts, model)
    np.testing.assert_allclose(mine[0], theirs, atol=1e-9)
    np.testing.assert_allclose(depth[0], their_depth, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    theta=hnp.arrays(np.float64, st.integers(1, 9), elements=thetas),
    phi=hnp.arrays(np.float64, st.integers(1, 9), elements=phis),
)
def test_cameras_have_the_axes_of_the_shared_camera_model_to_the_last_bit(theta, phi):
    """PinholeCameras.at writes camera_axes out for speed; refinement results depend on the bits."""
    count = min(len(theta), len(phi))
    theta, phi = theta[:count], phi[:count]
    cams = PinholeCameras.at(theta, phi, CAMERA)
    right, down, forward = camera_axes(theta, phi)
    np.testing.assert_array_equal(cams.rotation, np.stack([right, down, forward], axis=-2))
    np.testing.assert_array_equal(cams.position, -forward * CAMERA.radius)
    np.testing.assert_array_equal(cams.unit_positions, pose_to_cartesian(theta, phi))
    np.testing.assert_array_equal(
        PinholeCameras.at(theta[0], phi[0], CAMERA).rotation, cams.rotation[:1]
    )


@settings(max_examples=60, deadline=None)
@given(theta=thetas, phi=phis, pts=points)
def test_directions_invert_projection(theta, phi, pts):
    cams = PinholeCameras.at(theta, phi, CAMERA)
    pixels, depth = cams.project(pts)
    rays = cams.directions(cams.normalised(pixels))[0]
    np.testing.assert_allclose(cams.position[0] + depth[0][:, None] * rays, pts, atol=1e-9)


def sampled_box(cams: PinholeCameras, surface: np.ndarray) -> np.ndarray:
    pixels, _ = cams.project(surface)
    return np.concatenate([pixels.min(axis=1), pixels.max(axis=1)], axis=-1)


def sphere_surface(centre: np.ndarray, radius: float, count: int = 200_000) -> np.ndarray:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(count, 3))
    return centre + radius * v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize(("theta", "phi"), [(0.0, 0.0), (30.0, 45.0), (60.0, 200.0), (85.0, 10.0)])
def test_sphere_boxes_are_the_exact_silhouette_bounds(theta, phi):
    cams = PinholeCameras.at(theta, phi, CAMERA)
    centre = np.array([2.0, -1.5, 0.5])
    exact = sphere_boxes(cams, centre[None], [0.5])[0, 0]
    sampled = sampled_box(cams, sphere_surface(centre, 0.5))[0]
    # Dense samples approach the silhouette from inside: within a fraction of a pixel.
    assert np.all(np.abs(exact - sampled) < 0.15)
    assert exact[0] <= sampled[0] + 1e-9
    assert exact[2] >= sampled[2] - 1e-9


def test_the_sphere_box_centre_is_the_projected_centre_pushed_outwards():
    """(a₁ + a₂)/2 = a_c / (1 − k²): the perspective shift the exact mapping removes."""
    cams = PinholeCameras.at(60.0, 30.0, CAMERA)
    centre = np.array([[2.5, 1.0, 0.45]])
    box = sphere_boxes(cams, centre, [0.45])[0, 0]
    projected, depth = cams.project(centre)
    k = 0.45 / depth[0, 0]
    a_c = (projected[0, 0, 0] - cams.cx) / cams.focal_px
    a_mid = ((box[0] + box[2]) / 2.0 - cams.cx) / cams.focal_px
    assert a_mid == pytest.approx(a_c / (1.0 - k**2), rel=1e-9)
    assert abs(a_mid - a_c) > 1e-4  # a visible, not a rounding, difference


@pytest.mark.parametrize("kind", [ProxyKind.PRISM, ProxyKind.CONE])
def test_prism_and_cone_boxes_bound_the_solid(kind):
    cams = PinholeCameras.at(50.0, 120.0, CAMERA)
    x, y, rho, height = 1.0, 0.5, 0.3, 0.8
    box = proxy_boxes(cams, [kind], [[x, y, rho, height]])[0, 0]
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 2 * np.pi, 100_000)
    t = rng.uniform(0, 1, 100_000)
    r = rho * (1 - t) if kind == ProxyKind.CONE else np.full_like(t, rho)
    solid = np.stack([x + r * np.cos(a), y + r * np.sin(a), height * t], axis=-1)
    sampled = sampled_box(cams, solid)[0]
    assert np.all(np.abs(box - sampled) < 0.5)


def rim_sample_boxes(
    cams: PinholeCameras, kind: int, x: float, y: float, rho: float, height: float
):
    """The definition of a prism or cone box: bounds of the projected rim samples (and apex),
    NaN when any sample is not in front of the camera."""
    a = np.linspace(0.0, 2.0 * np.pi, RIM_POINTS, endpoint=False)
    ring = np.stack([x + rho * np.cos(a), y + rho * np.sin(a)], axis=-1)
    base = np.column_stack([ring, np.zeros(RIM_POINTS)])
    if kind == ProxyKind.CONE:
        top = np.array([[x, y, height]])
    else:
        top = np.column_stack([ring, np.full(RIM_POINTS, height)])
    pixels, depth = cams.project(np.concatenate([base, top]))
    boxes = np.concatenate([pixels.min(axis=1), pixels.max(axis=1)], axis=-1)
    boxes[~(depth > 0.0).all(axis=1)] = np.nan
    return boxes


solids = hnp.arrays(
    np.float64,
    (5, 4),
    elements=st.floats(0.0, 1.0),
).map(lambda u: u * [8.0, 8.0, 1.5, 4.0] + [-4.0, -4.0, 0.05, 0.05])


@settings(max_examples=60, deadline=None)
@given(
    theta=hnp.arrays(np.float64, 7, elements=thetas),
    phi=hnp.arrays(np.float64, 7, elements=phis),
    params=solids,
    kinds=hnp.arrays(np.int_, 5, elements=st.sampled_from([1, 2])),
)
def test_prism_and_cone_boxes_are_the_bounds_of_their_rim_samples(theta, phi, params, kinds):
    """The per-camera ring and the bounds taken before scaling to pixels give the boxes of the
    plain definition, to rounding, including NaN for solids reaching behind a camera."""
    cams = PinholeCameras.at(
        theta, phi, CameraSpec(fov_deg=60.0, width=320, height=240, radius=3.0)
    )
    boxes = proxy_boxes(cams, kinds, params)
    for m, (kind, row) in enumerate(zip(kinds, params, strict=True)):
        expected = rim_sample_boxes(cams, int(kind), *row)
        np.testing.assert_array_equal(np.isnan(boxes[:, m]), np.isnan(expected))
        np.testing.assert_allclose(boxes[:, m], expected, rtol=1e-9, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(
    theta=thetas,
    phi=phis,
    params=solids,
    kinds=hnp.arrays(np.int_, 5, elements=st.sampled_from([0, 1, 2])),
)
def test_an_objects_box_does_not_depend_on_the_others(theta, phi, params, kinds):
    """Bit for bit: the Gauss-Newton mapping batches its finite differences with the residuals."""
    cams = PinholeCameras.at(theta, phi, CAMERA)
    together = proxy_boxes(cams, kinds, params)
    for m in range(len(kinds)):
        alone = proxy_boxes(cams, kinds[m : m + 1], params[m : m + 1])[:, 0]
        np.testing.assert_array_equal(together[:, m], alone)


@settings(max_examples=30, deadline=None)
@given(
    theta=hnp.arrays(np.float64, 40, elements=thetas),
    phi=hnp.arrays(np.float64, 40, elements=phis),
    params=solids,
    kinds=hnp.arrays(np.int_, 5, elements=st.sampled_from([0, 1, 2])),
)
def test_boxes_do_not_depend_on_how_the_cameras_are_chunked(theta, phi, params, kinds):
    """Bit for bit: grids larger than one pass of rim samples are split into passes."""
    cams = PinholeCameras.at(theta, phi, CAMERA)
    whole = proxy_boxes(cams, kinds, params)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(proxies, "_CHUNK_SAMPLES", 7 * 2 * 5 * RIM_POINTS)  # passes of 7 cameras
        chunked = proxy_boxes(cams, kinds, params)
    np.testing.assert_array_equal(chunked, whole)


@settings(max_examples=40, deadline=None)
@given(theta=thetas, phi=phis, pts=points)
def test_the_camera_frame_transforms_like_to_camera(theta, phi, pts):
    cams = PinholeCameras.at([theta, 90.0 - theta], [phi, phi + 90.0], CAMERA)
    origin, axes = cams.frame
    mine = origin[:, :, None] + np.einsum("cjn,pj->cnp", axes, pts)
    np.testing.assert_allclose(mine.transpose(1, 2, 0), cams.to_camera(pts), atol=1e-12)


def test_kinds_of_classes():
    assert kind_of("sphere") == ProxyKind.SPHERE
    assert kind_of("cone") == ProxyKind.CONE
    assert {kind_of(c) for c in ("cube", "cylinder", "mesh", "teapot")} == {ProxyKind.PRISM}


def test_clip_boxes_reports_the_fraction_inside():
    clipped, inside = clip_boxes([[-10.0, 0.0, 10.0, 10.0], [400.0, 0, 420, 10]], 320, 240)
    np.testing.assert_allclose(clipped[0], [0.0, 0.0, 10.0, 10.0])
    assert inside[0] == pytest.approx(0.5)
    assert np.isnan(clipped[1]).all()
    assert inside[1] == 0.0
