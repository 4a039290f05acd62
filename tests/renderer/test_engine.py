"""The render engine against its own ground truth and the camera model: exact silhouettes,
determinism, in-place camera moves without recompilation, and scalar/LLVM agreement."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from services.common.catalog import SceneCatalog
from services.common.geometry.camera import pinhole_camera
from services.common.geometry.pose import Pose
from services.renderer.engine import RenderEngine
from services.renderer.pool import WORKER_NICE
from services.renderer.variant import SCALAR_VARIANT
from tests.support import ROOT

POSES = [Pose(theta_deg=t, phi_deg=p) for t, p in [(0, 0), (30, 75), (52.5, 200), (82.5, 310)]]


@pytest.mark.parametrize("pose", POSES, ids=str)
def test_sphere_boxes_are_centred_on_the_projected_centres(engine, catalog, pose):
    scene = catalog.get("demo")
    ann = engine.annotate(scene, pose, 320, 240, None)
    checked = 0
    for obj in ann.objects:
        assert obj.box is not None
        x1, y1, x2, y2 = obj.box
        if x1 <= 0 or y1 <= 0 or x2 >= 320 or y2 >= 240 or obj.visible_fraction < 1.0:
            continue  # clipped or occluded boxes are not symmetric about the centre
        u, v = obj.projected_center
        assert abs((x1 + x2) / 2 - u) < 1.0, obj
        assert abs((y1 + y2) / 2 - v) < 1.0, obj
        checked += 1
    assert checked >= 3


@pytest.mark.parametrize("scene_id", ["demo", "garden"])
def test_annotations_are_consistent(engine, catalog, scene_id):
    scene = catalog.get(scene_id)
    grid = scene.spec.search.grid()
    rng = np.random.default_rng(7)
    for flat in rng.choice(grid.size, size=6, replace=False):
        index = grid.unflat(int(flat))
        pose = grid.pose(index)
        ann = engine.annotate(scene, pose, 320, 240, index)
        assert ann.grid_index == index
        assert ann.camera == pinhole_camera(pose, scene.spec.camera.radius, 45.0, 320, 240)
        assert [o.name for o in ann.objects] == [o.name for o in scene.spec.objects]
        for obj in ann.objects:
            assert obj.visible_pixels <= obj.full_pixels
            assert 0.0 <= obj.visible_fraction <= 1.0
            if obj.box is not None:
                assert obj.full_box is not None
                bx1, by1, bx2, by2 = obj.box
                fx1, fy1, fx2, fy2 = obj.full_box
                assert fx1 <= bx1
                assert fy1 <= by1
                assert bx2 <= fx2
                assert by2 <= fy2
                assert (bx2 - bx1) * (by2 - by1) >= obj.visible_pixels
            if obj.visible_fraction == 1.0:
                assert obj.box == obj.full_box
            u, v = obj.projected_center
            if obj.full_box is not None and 0 < u < 320 and 0 < v < 240:
                fx1, fy1, fx2, fy2 = obj.full_box
                assert fx1 - 1 <= u <= fx2 + 1, obj
                assert fy1 - 1 <= v <= fy2 + 1, obj


def test_centroids_match_the_scene_geometry(engine, catalog):
    scene = catalog.get("garden")
    ann = engine.annotate(scene, Pose(theta_deg=30, phi_deg=0), 320, 240, None)
    by_name = {o.name: o for o in ann.objects}
    assert by_name["red"].centroid == pytest.approx((1.0, -0.5, 0.4), abs=1e-4)
    assert by_name["post"].centroid == pytest.approx((0.5, 2.0, 0.45), abs=1e-4)
    assert by_name["hat"].centroid[2] == pytest.approx(0.4, abs=1e-4)
    duck = by_name["duck"]
    assert duck.centroid[:2] == pytest.approx((-2.0, -1.5), abs=1e-3)  # mesh recentred on its foot
    assert duck.centroid[2] > 0.2  # and resting on the ground


def test_the_same_seed_gives_the_same_image(engine, catalog):
    scene = catalog.get("demo")
    pose = Pose(theta_deg=45, phi_deg=30)
    a = engine.render(scene, pose, 160, 120, 4, seed=11).rgb
    b = engine.render(scene, pose, 160, 120, 4, seed=11).rgb
    c = engine.render(scene, pose, 160, 120, 4, seed=12).rgb
    assert a.shape == (120, 160, 3)
    assert a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_moving_the_camera_does_not_recompile_kernels(engine, catalog):
    if engine.variant == SCALAR_VARIANT:
        pytest.skip("the scalar variant compiles no kernels")
    import drjit as dr

    scene = catalog.get("demo")
    engine.render(scene, Pose(theta_deg=20, phi_deg=10), 320, 240, 4, seed=0)  # warm

    def history_of_next_render(pose: Pose, seed: int) -> list[dict]:
        engine.call(dr.set_flag, dr.JitFlag.KernelHistory, True)
        engine.call(dr.kernel_history_clear)
        engine.render(scene, pose, 320, 240, 4, seed=seed)
        history = engine.call(dr.kernel_history)
        engine.call(dr.set_flag, dr.JitFlag.KernelHistory, False)
        return [k for k in history if k["type"] == dr.KernelType.JIT]

    for pose, seed in [(Pose(theta_deg=60, phi_deg=200), 1), (Pose(theta_deg=7.5, phi_deg=0), 2)]:
        kernels = history_of_next_render(pose, seed)
        assert kernels, "the render launched no kernel"
        assert all(k["cache_hit"] for k in kernels), kernels


def test_frozen_renders_are_the_traced_renders_and_record_once(engine, traced_engine, catalog):
    """Replaying the frozen render gives the very pixels of tracing it again, for every pose
    and seed, and new poses and seeds replay the recording instead of recording anew."""
    scene = catalog.get("garden")
    views = [
        (Pose(theta_deg=t, phi_deg=p), seed)
        for t, p, seed in ((30, 40, 0), (55, 300, 1), (10, 120, 7), (75, 200, 99), (45, 10, 3))
    ]
    recordings = []
    for pose, seed in views:
        frozen = engine.render(scene, pose, 176, 132, 3, seed)  # a film no other test uses
        recordings.append(engine.frozen_recordings)
        again = traced_engine.render(scene, pose, 176, 132, 3, seed)
        assert np.array_equal(frozen.rgb, again.rgb)
    assert traced_engine.frozen_recordings == 0
    # Values that change between calls become recording inputs after their first change
    # (dr.freeze's auto_opaque); from then on new views replay the recording.
    assert recordings[2:] == [recordings[2]] * 3, recordings


def test_a_frozen_render_of_another_film_is_traced_again(
    engine, traced_engine, catalog, monkeypatch
):
    """Should a frozen replay come out at another film's size (a recording of a scene alike in
    layout: seen once, under load, among drone lenses' padded films), the pass is traced again:
    the film asked for, with the very pixels of tracing it, and no error."""
    scene = catalog.get("garden")
    pose = Pose(theta_deg=35, phi_deg=70)

    def stale(mi_scene, sensor, seed, spp, key):  # another film's recording, replayed
        _, _, width, height = key
        return np.zeros((height + 64, width + 64, 3), dtype=np.float32)

    monkeypatch.setattr(engine, "_render_view", stale)
    image = engine.render(scene, pose, 96, 72, 2, 5)
    monkeypatch.undo()
    again = traced_engine.render(scene, pose, 96, 72, 2, 5)
    assert image.rgb.shape == (72, 96, 3)
    assert np.array_equal(image.rgb, again.rgb)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="threads are found in /proc")
def test_jit_worker_threads_run_at_low_priority_after_a_render(engine, catalog):
    """Dr.Jit's workers spin after each launch; at nice 19 the spin yields to the detector."""
    if engine.variant == SCALAR_VARIANT:
        pytest.skip("the scalar variant has no worker pool")
    own = os.getpriority(os.PRIO_PROCESS, 0)  # this thread's nice value
    engine.render(catalog.get("demo"), Pose(theta_deg=40, phi_deg=10), 64, 48, 1)
    workers = [
        int(task.name)
        for task in Path("/proc/self/task").iterdir()
        if (task / "comm").read_text().startswith("nt [")
    ]
    assert workers, "no Dr.Jit worker thread found"
    assert {os.getpriority(os.PRIO_PROCESS, tid) for tid in workers} == {WORKER_NICE}
    assert os.getpriority(os.PRIO_PROCESS, 0) == own  # the rest of the process is untouched


def test_the_scalar_variant_gives_the_same_ground_truth(engine, catalog):
    """A separate process on ``scalar_rgb`` must see the same silhouettes as this one."""
    script = (
        "import json\n"
        "from services.common.geometry.pose import Pose\n"
        "from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog\n"
        "from services.renderer.engine import RenderEngine\n"
        "e = RenderEngine('scalar_rgb'); e.start()\n"
        "s = SceneCatalog([BUILTIN_SCENES_DIR]).get('garden')\n"
        "a = e.annotate(s, Pose(theta_deg=37.5, phi_deg=100), 160, 120, None)\n"
        "print(json.dumps({'variant': e.variant, 'ann': a.model_dump(mode='json')}))\n"
        "e.close()\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=240
    )
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["variant"] == SCALAR_VARIANT
    mine = engine.annotate(catalog.get("garden"), Pose(theta_deg=37.5, phi_deg=100), 160, 120, None)
    for theirs, ours in zip(result["ann"]["objects"], mine.objects, strict=True):
        assert theirs["name"] == ours.name
        assert theirs["visible_pixels"] == pytest.approx(ours.visible_pixels, rel=0.02, abs=3)
        assert theirs["box"] == pytest.approx(list(ours.box), abs=1.0)


def test_objects_sharing_a_material_stay_separate(engine, tmp_path):
    """Mitsuba merges meshes with identical materials unless told not to; each object must keep
    its own silhouette."""
    (tmp_path / "twins.yaml").write_text(
        "camera: {fov_deg: 45, width: 160, height: 120, radius: 8.0}\n"
        "lighting: {point: {position: [3, 3, 8], intensity: 200}}\n"
        "ground: {size: 12, color: [0.5, 0.5, 0.5]}\n"
        "objects:\n"
        "  - {name: a, shape: cube, position: [-1.5, 0], size: 0.8, color: [0.8, 0.1, 0.1]}\n"
        "  - {name: b, shape: cube, position: [1.5, 0], size: 0.8, color: [0.8, 0.1, 0.1]}\n"
        "  - {name: c, shape: cone, position: [0, 1.5], radius: 0.4, height: 0.8,\n"
        "     color: [0.8, 0.1, 0.1]}\n"
    )
    scene = SceneCatalog([tmp_path]).get("twins")
    ann = engine.annotate(scene, Pose(theta_deg=30, phi_deg=90), 160, 120, None)
    boxes = [o.box for o in ann.objects]
    assert all(box is not None for box in boxes)
    assert len(set(boxes)) == 3
    a, b = ann.objects[0], ann.objects[1]
    assert a.centroid[0] == pytest.approx(-1.5, abs=1e-4)
    assert b.centroid[0] == pytest.approx(1.5, abs=1e-4)


def test_object_map_agrees_with_the_annotations(engine, catalog):
    scene = catalog.get("garden")
    pose = Pose(theta_deg=60, phi_deg=250)
    ids = engine.object_map(scene, pose, 200, 150)
    ann = engine.annotate(scene, pose, 200, 150, None)
    assert ids.shape == (150, 200)
    for index, obj in enumerate(ann.objects):
        assert int((ids == index).sum()) == obj.visible_pixels
        if obj.box is not None:
            ys, xs = np.nonzero(ids == index)
            assert obj.box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)


def test_a_render_in_sample_passes_is_the_same_estimate(engine, catalog):
    """Split into sixteen 1-spp passes (slices of 4096 samples), a render is still
    deterministic, and differs from the one-call render by noise only: no more than two
    one-call renders of different seeds differ."""
    sliced = RenderEngine(engine.variant, slice_samples=4096)
    sliced.start()
    try:
        scene = catalog.get("demo")
        pose = Pose(theta_deg=35, phi_deg=70)
        first = sliced.render(scene, pose, 160, 120, 16, seed=5)
        again = sliced.render(scene, pose, 160, 120, 16, seed=5).rgb
        one = engine.render(scene, pose, 160, 120, 16, seed=5).rgb.astype(np.float64)
        other = engine.render(scene, pose, 160, 120, 16, seed=6).rgb.astype(np.float64)
    finally:
        sliced.close()
    assert np.array_equal(first.rgb, again)
    split = first.rgb.astype(np.float64)
    noise = np.abs(one - other).mean()
    assert 0 < np.abs(split - one).mean() < 1.25 * noise
    assert abs(split.mean() - one.mean()) < 0.5
    assert first.render_ms > 0


def test_the_scene_cache_hits_and_keeps_the_most_recently_used(monkeypatch):
    """A (scene, film size) is loaded once and found again; past ``cache_size`` the least
    recently used goes (no Mitsuba needed: the loading itself is stood in for)."""
    engine = RenderEngine(SCALAR_VARIANT, cache_size=2)
    loads: list[tuple[str, int]] = []

    def load(scene, width, height):
        loads.append((scene.id, width))
        return object()

    monkeypatch.setattr(engine, "_load", load)
    demo, garden = (SimpleNamespace(id=name, version=1) for name in ("demo", "garden"))
    try:
        first = engine.loaded(demo, 320, 240)
        assert engine.loaded(demo, 320, 240) is first  # a hit: not loaded again
        engine.loaded(garden, 320, 240)
        engine.loaded(demo, 320, 240)  # demo is now the most recent
        engine.loaded(demo, 640, 480)  # garden, the least recently used, goes
        assert engine.loaded_scenes() == ("demo",)
        engine.loaded(garden, 320, 240)
        assert loads == [("demo", 320), ("garden", 320), ("demo", 640), ("garden", 320)]
    finally:
        engine.close()
