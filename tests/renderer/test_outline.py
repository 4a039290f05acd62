"""The outline shading in a view's geometry: the albedo lit from the camera, which no light of
the scene changes (what the dense refinement keeps of a render's edges)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosmos.bench.altered import alter_scene
from services.common.catalog import SceneCatalog
from services.common.geometry.free_camera import FreeCamera
from services.renderer.view import resolve_free_camera

W, H = 160, 120
CAMERA = FreeCamera(position=(5.0, -4.0, 4.0), look_at=(0.3, 0.2, 0.0), roll_deg=8.0, fov_deg=50.0)


def test_the_outline_shading_does_not_move_with_the_light(engine, catalog, tmp_path: Path):
    """The demo seen under its own light and under one turned and tilted away (the bench's
    ``photo`` copy): the colours change, the outline shading does not, pixel for pixel."""
    scene = catalog.get("demo")
    copy = alter_scene(scene, "photo", np.random.default_rng(4), tmp_path, "demo_lit")
    moved = SceneCatalog([tmp_path]).get(copy.id)
    views = [(s, resolve_free_camera(s, CAMERA, W, H)) for s in (scene, moved)]
    rgb = [engine.render(s, v, W, H, 4, 0).rgb.astype(np.int16) for s, v in views]
    geometry = [engine.depth(s, v, W, H) for s, v in views]
    assert np.mean(np.abs(rgb[0] - rgb[1])) > 2.0  # the light did change the picture
    first, second = (g.shading for g in geometry)
    assert first is not None
    assert second is not None
    assert first.shape == (H, W)
    assert first.dtype == np.uint8
    assert np.array_equal(first, second)
    hit = geometry[0].depth > 0.0
    assert not first[~hit].any()  # nothing hit: black
    assert np.median(first[geometry[0].objects >= 0]) > 20  # the objects are lit from the eye
