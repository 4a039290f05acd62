"""What every service app gets from ``service_app``: its start-up heap frozen while it runs, the
service token on a stage's routes (not on its probes), the liveness and readiness probes, a 405
whose ``Allow`` names every method the path takes, a query parameter given twice refused, and the
errors FastAPI answers itself declared in the OpenAPI schema."""

from __future__ import annotations

import gc
import importlib
import logging
import re
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import Any

import httpx
import pytest
from asgi_lifespan import LifespanManager
from fastapi import APIRouter, FastAPI
from pydantic import SecretStr, ValidationError

from services.common.auth import (
    PROBE_PATHS,
    SCHEME_NAME,
    MissingServiceTokenError,
    ServiceTokenSettings,
    bearer,
    new_token,
)
from services.common.http import Readiness, service_app
from services.controller.app import create_app as create_controller
from services.detector.app import create_app as create_detector
from services.optimizer.app import create_app as create_optimizer
from services.renderer.app import create_app as create_renderer

pytestmark = pytest.mark.anyio

TOKEN = new_token()


@asynccontextmanager
async def nothing(app: FastAPI) -> AsyncIterator[None]:
    yield


def echo_router() -> APIRouter:
    router = APIRouter()

    @router.post("/echo")
    async def echo(body: dict[str, Any]) -> dict[str, Any]:
        return body

    @router.get("/health")
    async def health() -> dict[str, str]:
        return {"status": "ok"}

    return router


def app_with(
    token: str | None = TOKEN,
    *,
    auth: str = "token",
    guarded: bool = True,
    readiness: Readiness | None = None,
) -> FastAPI:
    settings = ServiceTokenSettings(
        service_token=SecretStr(token) if token else None,
        service_auth=auth,  # type: ignore[arg-type]
    )
    return service_app(
        "test",
        "A test service.",
        nothing,
        echo_router(),
        1024,
        settings=settings,
        guarded=guarded,
        readiness=readiness,
    )


@asynccontextmanager
async def client_of(app: FastAPI) -> AsyncIterator[httpx.AsyncClient]:
    async with (
        LifespanManager(app) as running,
        httpx.AsyncClient(
            transport=httpx.ASGITransport(app=running.app), base_url="http://test"
        ) as client,
    ):
        yield client


async def test_the_start_up_heap_is_frozen_while_the_app_runs():
    built: list[object] = []

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        built.append([object() for _ in range(1000)])  # what a lifespan builds, e.g. a model
        yield

    settings = ServiceTokenSettings(service_token=SecretStr(TOKEN))
    app = service_app(
        "test",
        "A test service.",
        lifespan,
        APIRouter(),
        1024,
        settings=settings,
        guarded=True,
        readiness=None,
    )
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
async def test_a_method_a_path_does_not_take_is_a_405_naming_every_one_it_does(
    service, service_token
):
    app = importlib.import_module(SERVICES[service]).create_app()
    paths = declared_methods(app)
    assert paths
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app),
        base_url="http://test",
        headers=bearer(service_token),
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
async def test_a_query_parameter_given_twice_is_refused_naming_it(
    service, method, url, name, service_token
):
    """Refused before the route runs (the app's state is not even built here): FastAPI would
    take the last value of a parameter it reads."""
    app = importlib.import_module(SERVICES[service]).create_app()
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app),
        base_url="http://test",
        headers=bearer(service_token),
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
async def test_a_json_body_that_is_not_text_is_a_400_problem(service, path, service_token):
    app = importlib.import_module(SERVICES[service]).create_app()
    async with (
        LifespanManager(app) as running,
        httpx.AsyncClient(
            transport=httpx.ASGITransport(app=running.app),
            base_url="http://test",
            headers=bearer(service_token),
        ) as client,
    ):
        response = await client.post(
            path, content=b'{"scene": "\xff"}', headers={"Content-Type": "application/json"}
        )
    assert response.status_code == 400, response.text
    assert response.headers["content-type"] == "application/problem+json"


@pytest.mark.parametrize(
    ("headers", "detail"),
    [
        ({}, "needs the stack's service token"),
        ({"Authorization": f"Basic {TOKEN}"}, "needs the stack's service token"),
        ({"Authorization": "Bearer not-the-token-at-all"}, "wrong"),
        ({"Authorization": f"Bearer {TOKEN}x"}, "wrong"),
        ({"Authorization": f"Bearer {TOKEN[:-1]}"}, "wrong"),
        ({"Authorization": "Bearer"}, "needs the stack's service token"),
        ({"X-Cosmos-Service-Token": TOKEN}, "needs the stack's service token"),
    ],
)
async def test_a_stage_refuses_a_caller_without_the_token(headers, detail):
    async with client_of(app_with()) as client:
        for method, path in [("POST", "/echo"), ("GET", "/nowhere"), ("GET", "/openapi.json")]:
            response = await client.request(method, path, json={"a": 1}, headers=headers)
            assert response.status_code == 401, (path, response.text)
            assert response.headers["content-type"] == "application/problem+json"
            assert response.headers["www-authenticate"].startswith("Bearer")
            problem = response.json()
            assert problem["type"] == "urn:cosmos:problem:unauthorized"
            assert problem["instance"] == path
            assert detail in problem["detail"]
            assert TOKEN not in response.text


async def test_a_stage_serves_a_caller_with_the_token():
    async with client_of(app_with()) as client:
        for scheme in ("Bearer", "bearer", "BEARER"):
            headers = {"Authorization": f"{scheme} {TOKEN}"}
            response = await client.post("/echo", json={"a": 1}, headers=headers)
            assert response.status_code == 200, response.text
            assert response.json() == {"a": 1}
        assert (await client.get("/nowhere", headers=bearer(TOKEN))).status_code == 404
        assert (await client.get("/openapi.json", headers=bearer(TOKEN))).status_code == 200


async def test_the_probes_need_no_token():
    async with client_of(app_with()) as client:
        for path in sorted(PROBE_PATHS):
            response = await client.get(path)
            assert response.status_code == 200, (path, response.text)
            assert response.json()["status"] == "ok"


async def test_a_strangers_body_is_not_read():
    """Refused before the body limit looks at it: no 413 for a stranger, only 401."""
    async with client_of(app_with()) as client:
        response = await client.post("/echo", content=b"x" * 4096)
        assert response.status_code == 401
        response = await client.post("/echo", content=b"x" * 4096, headers=bearer(TOKEN))
        assert response.status_code == 413


async def test_without_a_token_a_service_does_not_start(monkeypatch, caplog):
    for guarded in (True, False):  # the controller needs it as much as the stages
        with (
            caplog.at_level(logging.ERROR),
            pytest.raises(MissingServiceTokenError, match="COSMOS_SERVICE_AUTH=off"),
        ):
            async with LifespanManager(app_with(None, guarded=guarded)):
                pass
        assert "COSMOS_SERVICE_TOKEN is not set" in caplog.text


async def test_auth_off_serves_every_caller_and_says_so(caplog):
    with caplog.at_level(logging.WARNING):
        async with client_of(app_with(None, auth="off")) as client:
            response = await client.post("/echo", json={"a": 1})
            assert response.status_code == 200
    assert "COSMOS_SERVICE_AUTH=off" in caplog.text
    assert "securitySchemes" not in app_with(None, auth="off").openapi().get("components", {})


async def test_the_controller_asks_no_token_of_its_callers():
    async with client_of(app_with(guarded=False)) as client:
        assert (await client.post("/echo", json={"a": 1})).status_code == 200


@pytest.mark.parametrize("value", ["short", "x" * 15])
def test_a_short_token_is_refused(value):
    with pytest.raises(ValidationError, match="shorter than 16"):
        ServiceTokenSettings(service_token=SecretStr(value))


def test_an_empty_token_is_no_token():
    settings = ServiceTokenSettings(service_token=SecretStr(""))
    assert settings.service_token is None
    with pytest.raises(MissingServiceTokenError):
        settings.token()


STAGES = {"renderer": create_renderer, "detector": create_detector, "optimizer": create_optimizer}


@pytest.mark.parametrize("stage", STAGES)
def test_a_stages_openapi_declares_the_token(stage):
    schema = STAGES[stage]().openapi()
    assert schema["components"]["securitySchemes"][SCHEME_NAME] == {
        "type": "http",
        "scheme": "bearer",
        "description": "The stack's service token (COSMOS_SERVICE_TOKEN).",
    }
    operations = [
        (path, operation) for path, ops in schema["paths"].items() for operation in ops.values()
    ]
    assert {path for path, _ in operations} >= {"/health", "/livez", "/readyz"}
    for path, operation in operations:
        if path in PROBE_PATHS:
            assert "security" not in operation, path
            assert "401" not in operation["responses"], path
        else:
            assert operation["security"] == [{SCHEME_NAME: []}], path
            assert "application/problem+json" in operation["responses"]["401"]["content"]


def test_the_controllers_openapi_declares_open_probes_and_no_service_token():
    """The controller's public API takes API keys (its own scheme), never the service token."""
    schema = create_controller().openapi()
    assert SCHEME_NAME not in schema["components"].get("securitySchemes", {})
    for path in ("/livez", "/readyz"):
        operation = schema["paths"][path]["get"]
        assert "security" not in operation, path
        assert "401" not in operation["responses"], path
    assert "503" in schema["paths"]["/readyz"]["get"]["responses"]


async def test_readyz_says_why_not_in_problem_details():
    reasons: list[str] = ["the model is not loaded", "the disk is full"]

    async def readiness(app: FastAPI) -> Sequence[str]:
        return reasons

    async with client_of(app_with(readiness=readiness)) as client:
        response = await client.get("/readyz")
        assert response.status_code == 503
        assert response.headers["content-type"] == "application/problem+json"
        assert response.headers["retry-after"] == "1"
        problem = response.json()
        assert problem["type"] == "urn:cosmos:problem:not-ready"
        assert problem["detail"] == "the model is not loaded; the disk is full"
        assert problem["reasons"] == reasons
        assert (await client.get("/livez")).status_code == 200  # alive all the same
        reasons.clear()
        assert (await client.get("/readyz")).json() == {"status": "ok", "service": "test"}


async def test_readyz_is_no_before_the_start_and_when_the_check_fails(caplog):
    async def broken(app: FastAPI) -> Sequence[str]:
        raise RuntimeError("boom")

    app = app_with(readiness=broken)
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://test"
    ) as client:  # no lifespan: not started
        response = await client.get("/readyz")
        assert response.status_code == 503
        assert response.json()["reasons"] == ["starting or stopping"]
    with caplog.at_level(logging.ERROR):
        async with client_of(app) as client:
            response = await client.get("/readyz")
    assert response.status_code == 503
    assert response.json()["reasons"] == ["the readiness check failed; see the service's log"]
    assert "boom" in caplog.text
