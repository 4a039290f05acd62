"""The optimizer as a real uvicorn process over HTTP: a search end to end, and a schema-driven
fuzz of every route (no 5xx, answers match the OpenAPI schema)."""

from __future__ import annotations

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import positive_data_acceptance

from services.common.geometry.pose import GridIndex
from simulation import SceneSimulator
from tests.support import assert_token_required

pytestmark = pytest.mark.slow


def test_a_search_over_real_http(optimizer_process, catalog):
    scene = catalog.get("garden")
    simulator = SceneSimulator.from_scene(scene)
    grid = scene.spec.search.grid()
    views = simulator.grid_views(grid)

    def detections(flat: int) -> list[dict]:
        observation = simulator.observe(views, flat)
        return [d.model_dump(mode="json") for d in simulator.detections(observation)]

    target = grid.flat(GridIndex(lat=9, lon=31))
    history = [
        {
            "pose": {"lat": 2, "lon": 3},
            "image_size": [320, 240],
            "detections": detections(grid.flat(GridIndex(lat=2, lon=3))),
        }
    ]
    with httpx.Client(
        base_url=optimizer_process.url, timeout=60.0, headers=optimizer_process.headers
    ) as client:
        for _ in range(10):
            answer = client.post(
                "/next-pose",
                json={
                    "scene": "garden",
                    "target": {"image_size": [320, 240], "detections": detections(target)},
                    "history": history,
                },
            ).json()
            if answer["done"]:
                break
            index = answer["next"]["index"]
            history.append(
                {
                    "pose": index,
                    "image_size": [320, 240],
                    "detections": detections(grid.flat(GridIndex(**index))),
                }
            )
    assert answer["done"]
    assert answer["next"]["index"] == {"lat": 9, "lon": 31}
    assert len(history) <= 3


def test_the_optimizer_plans_for_holders_of_the_service_token_only(optimizer_process):
    ball = {"label": "sphere", "class_id": 0, "confidence": 0.9, "box": [100, 80, 140, 120]}
    body = {
        "scene": "demo",
        "target": {"image_size": [320, 240], "detections": [ball]},
        "history": [],
    }
    assert_token_required(optimizer_process, "POST", "/next-pose", json=body)
    assert_token_required(optimizer_process, "GET", "/strategies")


def test_every_route_answers_within_its_schema(optimizer_process):
    """Schema-driven fuzzing (schemathesis): valid and invalid inputs alike never get a 5xx and
    every answer matches the route's declared status codes, media types and schemas."""
    schema = schemathesis.openapi.from_url(
        f"{optimizer_process.url}/openapi.json", headers=optimizer_process.headers
    )
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) == 10
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(
            max_examples=20,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def fuzz(case: schemathesis.Case) -> None:
            # Schema-valid requests may still be refused with a 4xx problem: whether a box lies
            # inside its image, a scene exists, a visited pose is on the grid, or a grid and
            # history fit the service's caps, depends on values a static schema cannot relate.
            # Every other check stays on.
            case.call_and_validate(
                base_url=optimizer_process.url,
                headers=optimizer_process.headers,
                timeout=60,
                excluded_checks=[positive_data_acceptance],
            )

        fuzz()
