"""What every service app gets from ``service_app``: its start-up heap frozen while it runs, a 405
whose ``Allow`` names every method the path takes, a query parameter given twice refused, and the
errors FastAPI answers itself declared in the OpenAPI schema."""

from __future__ import annotations

import gc
import importlib
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import httpx
import pytest
from asgi_lifespan import LifespanManager
from fastapi import APIRouter, FastAPI

from services.common.http import service_app

pytestmark = pytest.mark.anyio


async def test_the_start_up_heap_is_frozen_while_the_app_runs():
    built: list[object] = []

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        built.append([object() for _ in range(1000)])  # what a lifespan builds, e.g. a model
        yield

    app = service_app("test", "A test service.", lifespan, APIRouter(), 1024)
    gc.unfreeze()
    async with LifespanManager(app):
        assert gc.get_freeze_count() > 1000
    assert gc.get_freeze_count() == 0  # unfrozen on shutdown: the app's leftovers can go


SERVICES = {
    "renderer": "services.renderer.app",
    "detector": "services.detector.app",
    "optimizer": "services.optimizer.app",
    "controller": "services.controller.app",
}


def declared_methods(app: FastAPI) -> dict[str, set[str]]:
    """Each path of ``app``'s OpenAPI schema (parameters filled in) and its methods."""
    paths: dict[str, set[str]] = {}
    for template, operations in app.openapi()["paths"].items():
        path = re.sub(r"\{[^}]+\}", "x", template)
        paths.setdefault(path, set()).update(method.upper() for method in operations)
    return paths


@pytest.mark.parametrize("service", SERVICES)
async def test_a_method_a_path_does_not_take_is_a_405_naming_every_one_it_does(service):
    app = importlib.import_module(SERVICES[service]).create_app()
    paths = declared_methods(app)
    assert paths
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://test"
    ) as client:
        for path, methods in paths.items():
            for method in {"GET", "POST", "PUT", "PATCH", "DELETE"} - methods:
                response = await client.request(method, path)
                assert response.status_code == 405, (method, path, response.text)
                assert response.headers["allow"] == ", ".join(sorted(methods)), (method, path)
                assert response.headers["content-type"] == "application/problem+json"
                assert response.json()["detail"].startswith(f"{method} is not allowed here")


# (service, a request whose query repeats a parameter, the parameter)
REPEATED = [
    ("renderer", "GET", "/health?verbose=1&verbose=2", "verbose"),
    ("detector", "POST", "/detect?conf=0.2&max_detections=3&conf=0.5", "conf"),
    ("optimizer", "POST", "/next-pose?strategy=a&strategy=b", "strategy"),
    ("controller", "GET", "/searches?limit=1&offset=0&limit=2", "limit"),
    ("controller", "GET", "/searches/x?x=1&x=1", "x"),
]


@pytest.mark.parametrize(("service", "method", "url", "name"), REPEATED)
async def test_a_query_parameter_given_twice_is_refused_naming_it(service, method, url, name):
    """Refused before the route runs (the app's state is not even built here): FastAPI would
    take the last value of a parameter it reads."""
    app = importlib.import_module(SERVICES[service]).create_app()
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://test"
    ) as client:
        response = await client.request(method, url)
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert problem["field"] == name
    assert problem["detail"] == f"{name}: '{name}' is given twice"


@pytest.mark.parametrize("service", SERVICES)
def test_the_errors_fastapi_answers_itself_are_declared_as_problems(service):
    """Every operation may answer 422 (an invalid or repeated parameter) and one with a JSON
    body 400 (a body that is not JSON text), each as problem+json like every other error, so
    that schema-driven clients and fuzzers (schemathesis) find what the service does."""
    schema = importlib.import_module(SERVICES[service]).create_app().openapi()
    assert "HTTPValidationError" not in schema.get("components", {}).get("schemas", {})
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            responses = operation["responses"]
            body = operation.get("requestBody", {}).get("content", {})
            expected = {"422"} | ({"400"} if "application/json" in body else set())
            assert expected <= set(responses), (method, path)
            for status, response in responses.items():
                if status.startswith(("4", "5")):
                    assert list(response["content"]) == ["application/problem+json"], (
                        method,
                        path,
                        status,
                    )


@pytest.mark.parametrize(
    ("service", "path"),
    [("optimizer", "/next-pose"), ("optimizer", "/map"), ("renderer", "/render")],
)
async def test_a_json_body_that_is_not_text_is_a_400_problem(service, path):
    app = importlib.import_module(SERVICES[service]).create_app()
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://test"
    ) as client:
        response = await client.post(
            path, content=b'{"scene": "\xff"}', headers={"Content-Type": "application/json"}
        )
    assert response.status_code == 400, response.text
    assert response.headers["content-type"] == "application/problem+json"
