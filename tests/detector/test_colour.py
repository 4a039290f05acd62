"""Colour measurement: synthetic objects on plain, noisy and tiled ground, and rendered scenes
checked against the renderer's objects."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.geometry.pose import Pose
from services.detector.colour import _far_from, _hue_consistent, _lab, _median, measure_colour
from tests.support import ROOT


def ground(kind: str, height: int = 200, width: int = 260, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "plain":
        return np.full((height, width, 3), 150, np.uint8)
    if kind == "noisy":
        noise = rng.normal(0, 12, (height, width, 1))
        gradient = np.linspace(110, 180, width)[None, :, None]
        return np.clip(gradient + noise, 0, 255).repeat(3, axis=2).astype(np.uint8)
    if kind == "tiles":
        tiles = cv2.imread(str(ROOT / "scenes" / "textures" / "tiles.png"), cv2.IMREAD_COLOR)
        assert tiles is not None
        tiles = cv2.cvtColor(tiles, cv2.COLOR_BGR2RGB)
        reps = (height // tiles.shape[0] + 1, width // tiles.shape[1] + 1, 1)
        return np.tile(tiles, reps)[:height, :width].copy()
    raise ValueError(kind)


def shaded_disc(image: np.ndarray, centre, radius: int, colour) -> np.ndarray:
    """Draw a Lambert-shaded disc (light from the upper left); its pixels' mean is returned."""
    height, width = image.shape[:2]
    y, x = np.mgrid[0:height, 0:width]
    dx, dy = (x + 0.5 - centre[0]) / radius, (y + 0.5 - centre[1]) / radius
    inside = dx**2 + dy**2 <= 1.0
    dz = np.sqrt(np.clip(1.0 - dx**2 - dy**2, 0.0, 1.0))
    light = np.array([-0.4, -0.5, 0.77])
    shade = np.clip(dx * light[0] + dy * light[1] + dz * light[2], 0.0, 1.0) * 0.8 + 0.2
    pixels = (np.asarray(colour, float)[None, :] * shade[inside][:, None]).round()
    image[inside] = pixels.astype(np.uint8)
    return pixels.mean(axis=0)


def disc_box(centre, radius):
    return (centre[0] - radius, centre[1] - radius, centre[0] + radius, centre[1] + radius)


@pytest.mark.parametrize("kind", ["plain", "noisy", "tiles"])
@pytest.mark.parametrize(
    "colour",
    [(220, 40, 40), (40, 200, 60), (40, 60, 220), (230, 210, 50), (30, 30, 30), (245, 245, 245)],
)
def test_shaded_disc_colour_on_any_ground(kind, colour):
    image = ground(kind)
    centre, radius = (130, 100), 40
    truth = shaded_disc(image, centre, radius, colour)
    measured = measure_colour(image, disc_box(centre, radius))
    assert measured is not None
    np.testing.assert_allclose(measured, truth, atol=12)


def test_flat_colour_is_exact():
    image = ground("plain")
    cv2.rectangle(image, (100, 60), (159, 139), (200, 30, 120), thickness=-1)
    assert measure_colour(image, (100, 60, 160, 140)) == (200.0, 30.0, 120.0)


def test_dark_grey_object_on_grey_ground():
    image = ground("noisy")
    truth = shaded_disc(image, (130, 100), 35, (70, 70, 70))
    measured = measure_colour(image, disc_box((130, 100), 35))
    assert measured is not None
    np.testing.assert_allclose(measured, truth, atol=12)


def test_an_occluder_of_another_hue_is_left_out():
    image = ground("plain")
    truth = shaded_disc(image, (130, 100), 40, (40, 60, 220))
    cv2.circle(image, (165, 135), 18, (230, 200, 40), thickness=-1)  # yellow over one corner
    measured = measure_colour(image, disc_box((130, 100), 40))
    assert measured is not None
    np.testing.assert_allclose(measured, truth, atol=15)


def test_a_box_of_ground_has_no_colour():
    image = ground("plain")
    assert measure_colour(image, (50, 50, 120, 120)) is None


@pytest.mark.parametrize("box", [(10, 10, 11.4, 30), (5.0, 5.0, 5.0, 5.0), (-50, -50, -10, -10)])
def test_tiny_or_outside_boxes_have_no_colour(box):
    assert measure_colour(ground("noisy"), box) is None


def test_a_box_filling_the_image_still_works():
    image = np.full((60, 80, 3), 120, np.uint8)
    cv2.circle(image, (40, 30), 22, (250, 90, 10), thickness=-1)
    measured = measure_colour(image, (0, 0, 80, 60))
    assert measured is not None
    np.testing.assert_allclose(measured, (250, 90, 10), atol=1)


@given(
    seed=st.integers(0, 2**32 - 1),
    size=st.tuples(st.integers(1, 60), st.integers(1, 60)),
    box=st.tuples(*[st.floats(-20, 80, allow_nan=False)] * 4),
    blobs=st.integers(0, 6),
)
@settings(max_examples=150, deadline=None, database=None)
def test_any_image_and_box_give_a_colour_or_none(seed, size, box, blobs):
    """Noise, specks, flat patches, boxes in or out of the image: a colour in range or None."""
    rng = np.random.default_rng(seed)
    width, height = size
    image = np.full((height, width, 3), rng.integers(0, 256, 3), np.uint8)
    if seed % 3 == 0:
        image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    for _ in range(blobs):
        x, y = rng.integers(0, width), rng.integers(0, height)
        image[y : y + rng.integers(1, 6), x : x + rng.integers(1, 6)] = rng.integers(0, 256, 3)
    x1, x2 = sorted(box[::2])
    y1, y2 = sorted(box[1::2])
    colour = measure_colour(image, (x1, y1, x2, y2))
    assert colour is None or all(0.0 <= c <= 255.0 for c in colour)


@given(
    seed=st.integers(0, 2**32 - 1),
    sizes=st.tuples(st.integers(1, 300), st.integers(1, 400)),
    delta_e=st.sampled_from([0.0, 2.3, 12.0, 12.3, 40.0]),
)
@settings(max_examples=100, deadline=None, database=None)
def test_far_from_ground_decides_as_brute_force(seed, sizes, delta_e):
    """The pruned matrix-product search decides exactly as ``cv2.batchDistance``, also for
    points at the limit (within float32 rounding of ``delta_e`` from a ground colour)."""
    rng = np.random.default_rng(seed)
    m, n = sizes
    ground = np.clip(rng.normal(rng.integers(0, 256, 3), 25, (m, 3)), 0, 255).astype(np.uint8)
    palette = _lab(ground)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    offset = rng.choice([0.0, 1e-7, -1e-7, 1e-5, -1e-5, 0.3, -0.3, 2.0], (n, 1))
    points = palette[rng.integers(0, m, n)] + direction * delta_e * (1.0 + offset)
    points = np.concatenate([points.astype(np.float32), _lab(rng.integers(0, 256, (50, 3)))])
    nearest, _ = cv2.batchDistance(points, palette, cv2.CV_32F, normType=cv2.NORM_L2SQR, K=1)
    np.testing.assert_array_equal(_far_from(points, palette, delta_e), nearest[:, 0] > delta_e**2)


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_median_is_numpy_median(n):
    values = np.random.default_rng(n).normal(20, 10, n).astype(np.float32)
    assert _median(values) == float(np.median(values))


def test_hue_consistency_is_the_hue_angle_test():
    """Keeping ``a cos h + b sin h >= chroma cos 35°`` is keeping hues within 35° of ``h``."""
    rng = np.random.default_rng(3)
    hue = rng.normal(1.0, 0.6, 5000)
    chroma = rng.uniform(5, 60, 5000)
    a, b = (chroma * np.cos(hue)).astype(np.float32), (chroma * np.sin(hue)).astype(np.float32)
    keep = _hue_consistent(a, b, np.hypot(a, b))
    mean_hue = np.arctan2(float(b.sum()), float(a.sum()))
    gap = np.abs(np.angle(np.exp(1j * (np.arctan2(b, a) - mean_hue))))
    median = float(np.median(np.hypot(a, b)))
    expected = (gap <= np.radians(35.0)) & (np.hypot(a, b) >= 0.25 * median)
    clear = np.abs(gap - np.radians(35.0)) > 1e-5  # away from float rounding at the edge
    np.testing.assert_array_equal(keep[clear], expected[clear])
    assert clear.sum() > 4900


def srgb8(linear) -> np.ndarray:
    c = np.asarray(linear, dtype=np.float64)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def hue_matched_mean(rgb: np.ndarray, box, linear) -> tuple[np.ndarray, int]:
    """The mean of the pixels inside ``box`` whose hue is the object's (from its linear RGB
    reflectance) and which are clearly coloured: the renderer's object pixels, read from the
    image alone (the scenes' grounds are grey or beige, far in hue or saturation)."""
    x1, y1, x2, y2 = (int(round(v)) for v in box)
    patch = rgb[y1:y2, x1:x2]
    hsv = cv2.cvtColor(patch, cv2.COLOR_RGB2HSV).astype(np.int32)
    ref = cv2.cvtColor(srgb8(linear).reshape(1, 1, 3), cv2.COLOR_RGB2HSV)[0, 0].astype(int)
    gap = np.abs(hsv[..., 0] - ref[0])
    gap = np.minimum(gap, 180 - gap)
    mask = (gap <= 10) & (hsv[..., 1] >= 90) & (hsv[..., 2] >= 30)
    return patch[mask].astype(float).mean(axis=0), int(mask.sum())


POSES = [(35.0, 20.0), (55.0, 140.0), (70.0, 250.0), (20.0, 300.0)]


@pytest.mark.parametrize("scene_id", ["demo", "garden"])
def test_rendered_object_colours(engine, catalog, scene_id):
    """Every well-visible plain-coloured object's measured colour is within 25/255 per channel
    of the mean of its hue-matched pixels, and its hue is the object's."""
    scene = catalog.get(scene_id)
    compared = 0
    for theta, phi in POSES:
        pose = Pose(theta_deg=theta, phi_deg=phi)
        rgb = engine.render(scene, pose, 320, 240, 16, 0).rgb
        truth = engine.annotate(scene, pose, 320, 240, None)
        for spec, obj in zip(scene.spec.objects, truth.objects, strict=True):
            colour = getattr(spec, "color", None)
            if colour is None or obj.box is None or obj.visible_pixels < 100:
                continue
            if obj.visible_fraction < 0.6:
                continue
            measured = measure_colour(rgb, obj.box)
            assert measured is not None, (scene_id, pose, obj.name)
            reference, count = hue_matched_mean(rgb, obj.box, colour)
            assert count >= 50
            np.testing.assert_allclose(measured, reference, atol=25, err_msg=obj.name)
            compared += 1
    assert compared >= 12
