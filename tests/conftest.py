"""Fixtures every folder shares: the service token, the anyio backend, an in-process render
engine, the built-in catalog. A service's own fixtures live in its folder's conftest."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from services.common.auth import TOKEN_VARIABLE, new_token
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.controller.store import SearchStore, open_store
from services.renderer.engine import RenderEngine
from tests.postgres_server import PostgresServer, postgres_problem
from tests.support import skip_unless_on_ci


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


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresServer]:
    """A real PostgreSQL server for the session (:mod:`tests.postgres_server`); skipped only
    where it cannot be had (not root and not installed), and on CI (``CI`` set) failed then."""
    binaries, why = postgres_problem()
    skip_unless_on_ci(why, "the PostgreSQL tests")
    assert binaries is not None
    server = PostgresServer(binaries)
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh controller database, once of each back end: a SQLite file, then a schema of its
    own on the session's PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path}/db/controller.sqlite3"
    server: PostgresServer = request.getfixturevalue("postgres")
    return server.new_schema()


@pytest.fixture
def opened(request: pytest.FixtureRequest) -> Iterator[Callable[..., SearchStore]]:
    """Opens search stores on the URL given, or else on :func:`database_url` (the test then
    runs on both back ends); closed after the test."""
    stores: list[SearchStore] = []

    def open_(url: str | None = None, **options: Any) -> SearchStore:
        stores.append(open_store(url or request.getfixturevalue("database_url"), **options))
        return stores[-1]

    yield open_
    for store in stores:
        store.close()
