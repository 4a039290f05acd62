"""The optimizer's caches in the service path: a search's requests resend their history as new
JSON, and what is cached by content must hit there, stay bounded, and never change an answer."""

from __future__ import annotations

import pytest

from services.common.contracts.optimize import NextPoseRequest, NextPoseResponse, searchable_grid
from services.common.geometry.pose import GridIndex
from services.optimizer import layout
from services.optimizer.calibration import CalibrationStore
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.strategies import map_based, simple
from simulation import SceneSimulator

CACHES = {
    "simple": (simple._mapped_views, simple._scored_views),
    "paper": (layout._mapped_views, layout._candidate_profiles),
}
START = GridIndex(lat=5, lon=20)


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    spec = searchable_grid(scene.spec.search)
    simulator = SceneSimulator.from_scene(scene)
    return scene, spec, simulator, simulator.grid_views(spec.grid())


@pytest.fixture
def context() -> OptimizerContext:
    return OptimizerContext(calibrations=CalibrationStore.load(), catalog=None)


@pytest.fixture
def fresh_caches():
    for caches in CACHES.values():
        for cache in caches:
            cache.clear()
    map_based.grid_cameras.cache_clear()
    yield
    for caches in CACHES.values():
        for cache in caches:
            cache.clear()


def detections(simulator: SceneSimulator, observation) -> list[dict]:
    return [d.model_dump(mode="json") for d in simulator.detections(observation)]


def request_json(demo, strategy: str, target: list[dict], history: list[int]) -> str:
    """A /next-pose body as a client sends it: the whole history, every time."""
    scene, spec, simulator, views = demo
    grid, camera = spec.grid(), scene.spec.camera
    size = (camera.width, camera.height)
    visited = [
        {
            "image_size": size,
            "detections": detections(simulator, simulator.clean_observation(views, flat)),
            "pose": {"lat": grid.unflat(flat).lat, "lon": grid.unflat(flat).lon},
        }
        for flat in history
    ]
    return NextPoseRequest.model_validate(
        {
            "strategy": strategy,
            "camera": camera.model_dump(mode="json"),
            "grid": spec.model_dump(mode="json"),
            "target": {"image_size": size, "detections": target},
            "history": visited,
        }
    ).model_dump_json(exclude_none=True)


def search(demo, context, strategy: str, target: GridIndex) -> list[NextPoseResponse]:
    """One search through the service's planning, from a fixed start, each request parsed
    from its JSON (new objects every time) and carrying the whole history."""
    _, spec, simulator, views = demo
    grid = spec.grid()
    goal = detections(simulator, simulator.clean_observation(views, grid.flat(target)))
    history = [grid.flat(START)]
    answers = []
    for _ in range(30):
        body = request_json(demo, strategy, goal, history)
        answers.append(next_pose(NextPoseRequest.model_validate_json(body), context))
        if answers[-1].done:
            return answers
        history.append(grid.flat(answers[-1].next.index))
    raise AssertionError("the search did not finish")


def uncached(monkeypatch, strategy: str) -> None:
    """The strategy's caches emptied and kept empty: every answer computed afresh."""
    for cache in CACHES[strategy]:
        cache.clear()
        monkeypatch.setattr(cache, "put", lambda key, value: False)  # keeps nothing


@pytest.mark.usefixtures("fresh_caches")
def test_the_simple_searchs_caches_hit_in_the_service(demo, context, monkeypatch):
    """Within a search the reference view often stays an earlier one: its scores against the
    target are found again. A second search of the scene from the same start (every search
    starts at one pose unless told otherwise) finds the start view's map again."""
    mapped, scored = CACHES["simple"]
    first = search(demo, context, "simple", GridIndex(lat=9, lon=25))
    assert len(first) == 6
    assert (scored.hits, scored.misses) == (4, 2)
    assert mapped.hits == 0  # the scores hit first within one search
    second = search(demo, context, "simple", GridIndex(lat=7, lon=26))
    assert mapped.hits >= 1
    for cache in (mapped, scored):
        assert 0 < cache.currsize <= cache.maxsize
    uncached(monkeypatch, "simple")
    assert search(demo, context, "simple", GridIndex(lat=9, lon=25)) == first
    assert search(demo, context, "simple", GridIndex(lat=7, lon=26)) == second
    assert len(mapped) == len(scored) == 0


@pytest.mark.usefixtures("fresh_caches")
def test_the_paper_searchs_caches_hit_in_the_service(demo, context, monkeypatch):
    """Every request of a search resends the target: its distance profile is found again. The
    current view's mapping is found again when a view comes back (here: the start view of a
    second search)."""
    mapped, profiles = CACHES["paper"]
    first = search(demo, context, "paper", GridIndex(lat=0, lon=0))
    assert len(first) == 3
    assert (profiles.hits, profiles.misses) == (2, 1)
    assert mapped.hits == 0
    second = search(demo, context, "paper", GridIndex(lat=10, lon=30))
    assert mapped.hits >= 1
    for cache in (mapped, profiles):
        assert 0 < cache.currsize <= cache.maxsize
    uncached(monkeypatch, "paper")
    assert search(demo, context, "paper", GridIndex(lat=0, lon=0)) == first
    assert search(demo, context, "paper", GridIndex(lat=10, lon=30)) == second
    assert len(mapped) == len(profiles) == 0


@pytest.mark.usefixtures("fresh_caches")
def test_the_grid_caches_hit_in_the_service(demo, context):
    """The cameras and view directions of every grid pose, keyed by the grid's and camera's
    values: built once, then found by every request (here of a reprojection search)."""
    map_based._grid_units.cache_clear()
    answers = search(demo, context, "reprojection", GridIndex(lat=8, lon=18))
    assert len(answers) >= 2
    cameras, units = map_based.grid_cameras.cache_info(), map_based._grid_units.cache_info()
    assert (cameras.hits, cameras.misses) == (len(answers) - 1, 1)
    assert (units.hits, units.misses) == (2 * len(answers) - 1, 1)
    assert cameras.maxsize == units.maxsize == 16


@pytest.mark.usefixtures("fresh_caches")
def test_a_cached_reference_view_answers_as_a_fresh_one(demo, context):
    """A target between grid poses, seen from the nearest one: the fresh map refines the pose
    from that view; the map cached by the first request holds that request's objects, and must
    still be recognised as this view's own (it was not: the second answer lost the refinement)."""
    _, spec, simulator, _ = demo
    grid = spec.grid()
    flat = 100
    theta, phi = float(grid.theta_deg[flat]), float(grid.phi_deg[flat])
    target = detections(
        simulator, simulator.observe(simulator.views([theta + 2.0], [phi + 2.5]), 0)
    )
    body = request_json(demo, "simple", target, [flat])
    first = next_pose(NextPoseRequest.model_validate_json(body), context)
    again = next_pose(NextPoseRequest.model_validate_json(body), context)
    assert simple._scored_views.hits == 1
    assert first.estimate is not None
    assert first.estimate.theta_deg != theta  # refined off the grid
    assert again == first
