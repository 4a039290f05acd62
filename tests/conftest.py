"""Fixtures every folder shares: the anyio backend, an in-process render engine, the built-in
catalog, a real renderer process. A service's own fixtures live in its folder's conftest."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.launch import ServiceProcess, running_service
from services.renderer.engine import RenderEngine


@pytest.fixture(scope="session")
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture(scope="session")
def engine() -> Iterator[RenderEngine]:
    eng = RenderEngine("auto")
    eng.start()
    yield eng
    eng.close()


@pytest.fixture(scope="session")
def catalog() -> SceneCatalog:
    return SceneCatalog([BUILTIN_SCENES_DIR])


@pytest.fixture(scope="session")
def renderer_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A real renderer (uvicorn) on loopback with small caps, so fuzzing stays fast."""
    logs: Path = tmp_path_factory.mktemp("logs")
    env = {"COSMOS_RENDERER_MAX_SIDE": "640", "COSMOS_RENDERER_MAX_SAMPLES": str(640 * 480 * 16)}
    with running_service("services.renderer.app:app", logs, env) as service:
        yield service
