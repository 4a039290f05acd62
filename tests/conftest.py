"""Fixtures every folder shares: the service token, the anyio backend, an in-process render
engine, the built-in catalog. A service's own fixtures live in its folder's conftest."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from services.common.auth import TOKEN_VARIABLE, new_token
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.renderer.engine import RenderEngine


@pytest.fixture(scope="session", autouse=True)
def service_token() -> Iterator[str]:
    """The services run as deployed, with a service token (without one they do not start):
    in-process apps read it from the environment, processes inherit it."""
    with pytest.MonkeyPatch.context() as patch:
        token = new_token()
        patch.setenv(TOKEN_VARIABLE, token)
        yield token


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
