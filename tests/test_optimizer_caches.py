"""The optimizer's caches in the service path: a search's requests resend their history as new
JSON, and what is cached by content must hit there, stay bounded, and never change an answer."""

from __future__ import annotations

import pytest

from services.common.optimization import NextPoseRequest, search_grid
from services.optimizer.calibration import CalibrationStore
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.strategies import simple
from simulation import SceneSimulator


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    spec = search_grid(scene.spec.search)
    simulator = SceneSimulator.from_scene(scene)
    return scene, spec, simulator, simulator.grid_views(spec.grid())


@pytest.fixture
def context() -> OptimizerContext:
    return OptimizerContext(calibrations=CalibrationStore.load(), catalog=None)


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


def test_a_cached_reference_view_answers_as_a_fresh_one(demo, context):
    """A target between grid poses, seen from the nearest one: the fresh map refines the pose
    from that view; the map cached by the first request holds that request's objects, and must
    still be recognised as this view's own (it was not: the second answer lost the refinement)."""
    scene, spec, simulator, views = demo
    grid = spec.grid()
    flat = 100
    off_grid = simulator.views(
        [float(grid.theta_deg[flat]) + 2.0], [float(grid.phi_deg[flat]) + 2.5]
    )
    target = detections(simulator, simulator.observe(off_grid, 0))
    body = request_json(demo, "simple", target, [flat])
    simple._mapped_single_cached.cache_clear()
    first = next_pose(NextPoseRequest.model_validate_json(body), context)
    again = next_pose(NextPoseRequest.model_validate_json(body), context)
    assert simple._mapped_single_cached.cache_info().hits == 1
    assert first.estimate is not None
    assert first.estimate.theta_deg != float(grid.theta_deg[flat])  # refined off the grid
    assert again == first
