"""The offline simulator (:mod:`simulation`): its boxes against the renderer's silhouettes, its
noise, the built-in meshes it reads."""

from __future__ import annotations

import numpy as np
import pytest

from scene_assets import read_ply_vertices
from simulation import NoiseModel, SceneSimulator, srgb8


def iou(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union


@pytest.mark.parametrize("scene_id", ["demo", "garden"])
def test_simulated_boxes_match_the_renderer(engine, catalog, scene_id):
    """Unoccluded objects: IoU ≥ 0.9 with the renderer's exact silhouette boxes (median ≈ 1);
    objects the renderer shows partly hidden still overlap their simulated box well."""
    scene = catalog.get(scene_id)
    grid = scene.spec.search.grid()
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.grid_views(grid)
    whole, partly, missed = [], [], 0
    for flat in range(0, grid.size, 13):
        index = grid.unflat(flat)
        ann = engine.annotate(scene, grid.pose(index), 320, 240, index)
        for k, obj in enumerate(ann.objects):
            seen = views.visible[flat, k]
            if obj.box is None or obj.visible_pixels < 40:
                continue
            if not seen:
                missed += 1
            elif obj.visible_fraction >= 0.99:
                whole.append(iou(obj.box, views.boxes[flat, k]))
            else:
                partly.append(iou(obj.box, views.boxes[flat, k]))
    assert len(whole) >= 100
    assert min(whole) >= 0.9
    assert np.median(whole) >= 0.98
    assert np.median(partly) >= 0.8
    assert missed <= 1


def test_noise_is_seeded_and_does_what_it_says(catalog):
    scene = catalog.get("demo")
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.views([45.0], [30.0])
    clean = simulator.observe(views, 0)
    noise = NoiseModel(pixel_sigma=2.0, miss_rate=0.3, spurious_rate=1.0)
    a = simulator.observe(views, 0, noise, np.random.default_rng(5))
    b = simulator.observe(views, 0, noise, np.random.default_rng(5))
    assert a.labels == b.labels
    assert np.array_equal(a.boxes, b.boxes)
    assert len(clean) == 5
    counts = [len(simulator.observe(views, 0, noise, np.random.default_rng(s))) for s in range(200)]
    # 5 objects, 30 % missed, one spurious each: 4.5 on average.
    assert np.mean(counts) == pytest.approx(4.5, abs=0.25)
    gaps = []
    for seed in range(50):
        noisy = simulator.observe(
            views, 0, NoiseModel(pixel_sigma=2.0), np.random.default_rng(seed)
        )
        gaps.append(noisy.boxes - clean.boxes)
    assert np.std(gaps) == pytest.approx(2.0, rel=0.15)
    with pytest.raises(ValueError, match="random generator"):
        simulator.observe(views, 0, noise)


def test_detections_carry_class_and_srgb_colour(catalog):
    scene = catalog.get("demo")
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.views([30.0], [0.0])
    detections = simulator.detections(simulator.observe(views, 0))
    red = srgb8(scene.spec.objects[0].color)
    assert {d.label for d in detections} == {"sphere"}
    assert any(np.allclose(d.color, red) for d in detections)
    assert all(0 <= d.box[0] < d.box[2] <= 320 for d in detections)


def test_built_in_meshes_are_read(catalog):
    scene = catalog.get("garden")
    meshes = [path for field, path in scene.assets.items() if field.endswith(".file")]
    assert meshes
    for path in meshes:
        vertices = read_ply_vertices(path)
        assert vertices.dtype == np.float32
        assert vertices.shape[1] == 3
        assert len(vertices) > 3
        assert np.isfinite(vertices).all()
