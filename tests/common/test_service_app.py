"""What every service app gets from ``service_app``: its start-up heap frozen while it runs."""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

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
