"""What every service app gets from ``service_app``: its start-up heap frozen while it runs, and a
405 whose ``Allow`` names every method the path takes."""

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
