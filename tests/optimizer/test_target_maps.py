"""The target's maps kept between a free search's renders: ``refine_pose`` called again with
the same target (another render of the search) makes neither its grey image nor its distance
maps again and fits exactly as it did; another target, or a bound of 0, makes its own; a
target that cannot be decoded is refused and nothing is kept."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from services.common.contracts.free import FreePoseRequest
from services.common.contracts.optimize import ImageDetections
from services.common.contracts.refine import RefinePoseRequest
from services.common.errors import ServiceError
from services.common.geometry.free_camera import FreeCamera
from services.optimizer.free.target_maps import TargetMapCache
from services.optimizer.free_pose import SceneObjectCache, free_pose
from services.optimizer.refine_pose import ImageLimits, refine_pose
from services.renderer.view import resolve_free_camera
from tests.optimizer.test_dense import levels_made
from tests.optimizer.test_free_route import H, W, target

TRUTH = FreeCamera(position=(4.0, 5.0, 6.0), look_at=(-0.2, 0.4, 0.0), roll_deg=12.0, fov_deg=50.0)
LIMITS = ImageLimits(4096 * 4096, 16_384)


def _jpeg(rgb: np.ndarray, quality: int = 92) -> bytes:
    ok, data = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return data.tobytes()


@pytest.fixture(scope="module")
def case(engine, catalog) -> tuple[bytes, RefinePoseRequest, bytes]:
    """The target as a JPEG, the request refining its box pose (fov not given) and the render
    at that pose, as a free search sends them."""
    scene = catalog.get("demo")
    image = engine.render(scene, resolve_free_camera(scene, TRUTH, W, H), W, H, 16, 1).rgb
    boxes, _ = target(engine, catalog, "demo", TRUTH)
    target_boxes = ImageDetections.model_validate(boxes)
    answer = free_pose(
        FreePoseRequest(scene="demo", target=target_boxes), catalog, SceneObjectCache()
    )
    assert answer.pose is not None
    at = resolve_free_camera(scene, answer.pose.camera(), W, H)
    rendered = replace(engine.depth(scene, at, W, H), rgb=engine.render(scene, at, W, H, 8, 0).rgb)
    request = RefinePoseRequest(scene="demo", pose=answer.pose, fit_focal=True)
    return _jpeg(image), request, rendered.npz()


def _fit(answer) -> str:
    return json.dumps(answer.model_dump(mode="json"), sort_keys=True)


def test_a_second_render_of_the_search_finds_the_targets_maps(case, catalog, monkeypatch):
    target, request, render = case
    made = levels_made(monkeypatch)
    cache = TargetMapCache()
    objects = SceneObjectCache()
    first = refine_pose(request, target, render, catalog, objects, LIMITS, cache)
    assert sorted(made) == [1, 2, 4]  # the focal length fitted: every level
    made.clear()
    again = refine_pose(request, target, render, catalog, objects, LIMITS, cache)
    assert made == []
    assert cache.grays.hits == 1
    assert cache.levels.hits == 3
    stats = cache.stats()  # what the optimizer's /health says of it
    assert (stats.targets, stats.hits, stats.misses) == (1, 1, 1)
    assert 0 < stats.bytes <= stats.max_bytes == cache.grays.maxsize + cache.levels.maxsize
    assert _fit(again) == _fit(first)
    fresh = refine_pose(request, target, render, catalog, objects, LIMITS, TargetMapCache(0))
    assert sorted(made) == [1, 2, 4]
    assert _fit(fresh) == _fit(first)
    kept = cache.levels.lookup(cache.levels.keys()[0])
    assert kept is not None
    assert not kept.distance.flags.writeable


def test_another_target_makes_its_own_maps(case, catalog, monkeypatch):
    target, request, render = case
    cache = TargetMapCache()
    refine_pose(request, target, render, catalog, SceneObjectCache(), LIMITS, cache)
    made = levels_made(monkeypatch)
    rgb = cv2.imdecode(np.frombuffer(target, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    other = _jpeg(np.ascontiguousarray(rgb), quality=80)  # the same view, other bytes
    refine_pose(request, other, render, catalog, SceneObjectCache(), LIMITS, cache)
    assert sorted(made) == [1, 2, 4]
    assert len(cache.grays) == 2


def test_a_target_that_cannot_be_decoded_is_refused_and_not_kept(case, catalog):
    target, request, render = case
    cache = TargetMapCache()
    truncated = target[: len(target) // 3]
    with pytest.raises(ServiceError) as raised:
        refine_pose(request, truncated, render, catalog, SceneObjectCache(), LIMITS, cache)
    assert raised.value.status == 422
    assert raised.value.field == "target"
    assert len(cache.grays) == 0
    assert len(cache.levels) == 0
