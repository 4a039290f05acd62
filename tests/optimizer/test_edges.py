"""The render's edge points for the dense refinement: near the render's outline (object ids,
depth steps, outline shading), an edge the scene's light made (a cast shadow) is left out, and
silhouettes, occlusions and texture are kept."""

from __future__ import annotations

import cv2
import numpy as np

from benchmarks.target_maps import reference_level
from services.common.geometry.camera import PinholeCamera
from services.optimizer.free.edges import (
    OUTLINE_PX,
    edge_points,
    edge_points_by_outline,
    exact_distance,
    outline,
    target_level,
)

W, H = 120, 80
SHADOW_COL, OUTLINE_COL, TEXTURE_COL = 40, 80, 100


def _camera() -> PinholeCamera:
    """Straight down from 5 units (x right, y down, looking along -z)."""
    return PinholeCamera(
        width=W,
        height=H,
        fov_deg=60.0,
        fx=100.0,
        fy=100.0,
        cx=W / 2,
        cy=H / 2,
        rotation=((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0)),
        translation=(0.0, 0.0, 5.0),
        position=(0.0, 0.0, 5.0),
    )


def _images() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A render (colours, depth, object ids, outline shading) of the ground with a shadow on it
    and an object, with a painted stripe, of the ground's own brightness under the light (its
    outline shows in the ids alone) and of the ground's depth (a flat tile)."""
    rgb = np.full((H, W, 3), 160, np.uint8)
    rgb[:, SHADOW_COL:OUTLINE_COL] = 60  # the shadow
    rgb[:, OUTLINE_COL:] = 230  # the object
    rgb[:, TEXTURE_COL:] = 120  # its stripe
    objects = np.full((H, W), -1, np.int16)
    objects[:, OUTLINE_COL:] = 0
    shading = np.full((H, W), 150, np.uint8)
    shading[:, TEXTURE_COL:] = 90
    return rgb, np.full((H, W), 5.0, np.float32), objects, shading


def _near(columns: np.ndarray, col: int) -> np.ndarray:
    return np.abs(columns - col) <= OUTLINE_PX + 1


def _columns(points) -> np.ndarray:
    """The image columns of the edge points' world points (seen from :func:`_camera`)."""
    camera = _camera()
    in_camera = points.world @ np.asarray(camera.rotation).T + np.asarray(camera.translation)
    return camera.fx * in_camera[:, 0] / in_camera[:, 2] + camera.cx


def test_without_the_outline_every_colour_edge_is_kept():
    rgb, depth, _, _ = _images()
    columns = _columns(edge_points(rgb, depth, _camera()))
    for col in (SHADOW_COL, OUTLINE_COL, TEXTURE_COL):
        assert _near(columns, col).sum() >= H // 2


def test_near_the_outline_the_shadow_edge_goes_and_silhouette_and_texture_stay():
    rgb, depth, objects, shading = _images()
    near = outline(depth, objects, shading)
    on, _ = edge_points_by_outline(rgb, depth, _camera(), None, near)
    columns = _columns(on)
    assert not _near(columns, SHADOW_COL).any()
    assert _near(columns, OUTLINE_COL).sum() >= H // 2
    assert _near(columns, TEXTURE_COL).sum() >= H // 2
    assert np.all(_near(columns, OUTLINE_COL) | _near(columns, TEXTURE_COL))


def test_a_depth_step_is_an_outline_and_a_slope_is_not():
    """An occluding edge within one object (a step from 5 to 6 units) is outline; a plane
    seen obliquely (depth growing 2 % a pixel) is not."""
    depth = np.tile(np.geomspace(4.0, 4.0 * 1.02 ** (W - 1), W, dtype=np.float32), (H, 1))
    objects = np.zeros((H, W), np.int16)
    shading = np.full((H, W), 150, np.uint8)
    assert not outline(depth, objects, shading).any()
    depth[:, OUTLINE_COL:] = 6.0
    near = outline(depth, objects, shading)
    assert near[:, OUTLINE_COL].all()
    assert not near[:, : OUTLINE_COL - OUTLINE_PX - 1].any()


def test_distances_off_by_their_last_bit_are_made_exact():
    """OpenCV's threads leave the last float32 bit of an exact distance varying between calls;
    the target's maps take the float32 nearest √(dx² + dy²) instead, so a fit repeats."""
    squared = np.arange(0, 400, dtype=np.float64)  # every d² = dx² + dy² up to 20 px
    exact = np.sqrt(squared).astype(np.float32)
    for direction in (np.inf, -np.inf):
        jittered = np.nextafter(exact, np.float32(direction))
        assert not np.array_equal(jittered, exact)
        assert np.array_equal(exact_distance(jittered), exact)


def test_target_levels_hold_exact_distances():
    image = np.full((H, W), 90, np.uint8)
    cv2.circle(image, (40, 40), 22, 200, -1)
    cv2.rectangle(image, (70, 15), (105, 60), 30, -1)
    level = target_level(image, 1, 1.0, 5.0)
    below = level.distance < 5.0
    squared = level.distance[below].astype(np.float64) ** 2
    assert below.sum() > W * H  # edges in several orientation bins
    assert np.array_equal(level.distance[below], np.sqrt(np.rint(squared)).astype(np.float32))


def test_target_levels_are_numpys_gradients_of_the_exact_maps_bit_for_bit():
    """The level's in-place float32 arithmetic gives exactly what ``exact_distance`` and
    ``np.gradient`` give (a fit's basin can hang on a map's last bit), at every scale."""
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (0, 0), 3.0)
    cv2.circle(image, (40, 40), 22, 200, -1)
    cv2.rectangle(image, (70, 15), (105, 60), 30, -1)
    for scale, cap in ((1, 5.0), (2, 6.0), (4, 8.0), (1, 2.5)):
        level = target_level(image, scale, 1.0, cap)
        before = reference_level(image, scale, 1.0, cap)
        for name in ("distance", "grad_x", "grad_y"):
            assert getattr(level, name).tobytes() == getattr(before, name).tobytes(), name
