"""Fixtures every folder shares: the anyio backend, an in-process render engine, the built-in
catalog, a real renderer process. A service's own fixtures live in its folder's conftest."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
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
