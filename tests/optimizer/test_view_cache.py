"""The cache of view mappings: keyed by content, bounded, thread-safe, and invisible in the
answers (a search's later requests map only their new view)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from services.common.contracts.optimize import NextPoseRequest, TargetImage, VisitedView
from services.common.geometry.pose import PoseQuery
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import CalibrationStore
from services.optimizer.mapping import map_exact
from services.optimizer.observations import Observation
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.view_cache import ViewMappings
from simulation import NoiseModel, SceneSimulator

CAMERA = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)


def view(shift: float = 0.0) -> Observation:
    """A fresh object each call: equal content must hit, whatever object carries it."""
    return Observation.from_arrays(
        ["sphere", "cube", "cone"],
        [[100 + shift, 90, 130, 120], [180, 100, 220, 150], [40, 60, 70, 110]],
        [[200, 30, 30], [30, 200, 30], [30, 30, 200]],
    )


def test_a_view_is_mapped_once_whatever_object_carries_it():
    cache = ViewMappings()
    first = cache.get(view(), 45.0, 30.0, CAMERA)
    again = cache.get(view(), 45.0, 30.0, CAMERA)
    assert again is first
    assert (cache.hits, cache.misses, len(cache)) == (1, 1, 1)
    cache.get(view(), 45.0, 37.5, CAMERA)  # another pose
    cache.get(view(shift=1.0), 45.0, 30.0, CAMERA)  # another box
    cache.get(view(), 45.0, 30.0, CAMERA.model_copy(update={"radius": 9.0}))  # another camera
    assert (cache.hits, cache.misses, len(cache)) == (1, 4, 4)
    with pytest.raises(ValueError, match="read-only"):
        first.position[0, 0] = 0.0  # shared by every caller: nobody may change it


def test_the_cached_mapping_is_the_fresh_one():
    obs = view()
    cached = ViewMappings().get(obs, 52.5, 200.0, CAMERA)
    fresh = map_exact(obs.boxes, obs.kinds, CAMERA, 52.5, 200.0)
    for name in ("position", "offsets", "radius", "height", "sigma", "reliable"):
        np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name))


def test_the_cache_is_bounded_and_forgets_the_least_recently_used():
    cache = ViewMappings(maxsize=2)
    a, b, c = (view(shift=s) for s in (0.0, 1.0, 2.0))
    cache.get(a, 45.0, 0.0, CAMERA)
    cache.get(b, 45.0, 0.0, CAMERA)
    cache.get(a, 45.0, 0.0, CAMERA)  # a is now the most recent
    cache.get(c, 45.0, 0.0, CAMERA)  # evicts b
    assert len(cache) == 2
    misses = cache.misses
    cache.get(a, 45.0, 0.0, CAMERA)
    assert cache.misses == misses
    cache.get(b, 45.0, 0.0, CAMERA)
    assert cache.misses == misses + 1
    assert len(cache) == 2
    cache.clear()
    assert (len(cache), cache.hits, cache.misses) == (0, 0, 0)


def test_a_cache_of_size_zero_keeps_nothing():
    cache = ViewMappings(maxsize=0)
    cache.get(view(), 45.0, 0.0, CAMERA)
    cache.get(view(), 45.0, 0.0, CAMERA)
    assert (len(cache), cache.hits, cache.misses) == (0, 0, 2)
    with pytest.raises(ValueError, match="maxsize"):
        ViewMappings(maxsize=-1)


def test_threads_share_the_cache_safely():
    cache = ViewMappings(maxsize=3)
    views = [view(shift=float(s)) for s in range(5)]
    fresh = [map_exact(v.boxes, v.kinds, CAMERA, 30.0, 60.0).position for v in views]

    def work(i: int) -> bool:
        k = i % len(views)
        return np.array_equal(cache.get(views[k], 30.0, 60.0, CAMERA).position, fresh[k])

    with ThreadPoolExecutor(max_workers=4) as pool:
        assert all(pool.map(work, range(200)))
    assert len(cache) <= 3
    assert cache.hits + cache.misses == 200


@pytest.fixture(scope="module")
def search_requests(catalog) -> list[NextPoseRequest]:
    """A search's requests as the controller sends them: each carries the whole history."""
    scene = catalog.get("garden")
    grid = scene.spec.search.grid()
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.grid_views(grid)
    size = (scene.spec.camera.width, scene.spec.camera.height)
    goal = grid.size // 2 + 5
    noisy = simulator.observe(views, goal, NoiseModel(pixel_sigma=1.5), np.random.default_rng(3))
    target = TargetImage(image_size=size, detections=simulator.detections(noisy))
    history = []
    # Ending at the (noisy) target: the last answer refines the pose continuously.
    for flat in (0, grid.size // 3, grid.size - 7, goal):
        index = grid.unflat(flat)
        detections = simulator.detections(simulator.observe(views, flat))
        history.append(
            VisitedView(
                pose=PoseQuery(lat=index.lat, lon=index.lon), image_size=size, detections=detections
            )
        )
    return [
        NextPoseRequest(scene="garden", target=target, history=tuple(history[:k]))
        for k in range(1, len(history) + 1)
    ]


def test_a_search_maps_each_view_once_and_answers_as_without_the_cache(catalog, search_requests):
    calibrations = CalibrationStore.load()
    cached = OptimizerContext(calibrations=calibrations, catalog=catalog)
    answers = [next_pose(request, cached) for request in search_requests]
    views = len(search_requests)
    assert cached.mappings.misses == views  # every view mapped once ...
    assert cached.mappings.hits == views * (views - 1) // 2  # ... and found again after
    uncached = OptimizerContext(
        calibrations=calibrations, catalog=catalog, mappings=ViewMappings(maxsize=0)
    )
    assert [next_pose(request, uncached) for request in search_requests] == answers
    # The same answers again from the warm cache, in any order.
    assert [next_pose(request, cached) for request in reversed(search_requests)] == answers[::-1]
