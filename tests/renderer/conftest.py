"""The renderer's fixtures: a real renderer process, an engine that traces every render."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cosmos.launch import ServiceProcess, running_service
from services.renderer.engine import RenderEngine
from services.renderer.variant import SCALAR_VARIANT


@pytest.fixture(scope="session")
def renderer_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A real renderer (uvicorn) on loopback with small caps, so fuzzing stays fast."""
    logs: Path = tmp_path_factory.mktemp("logs")
    env = {"COSMOS_RENDERER_MAX_SIDE": "640", "COSMOS_RENDERER_MAX_SAMPLES": str(640 * 480 * 16)}
    with running_service("services.renderer.app:app", logs, env) as service:
        yield service


@pytest.fixture(scope="module")
def traced_engine(engine: RenderEngine) -> Iterator[RenderEngine]:
    """An engine of the shared engine's variant that traces every render (no frozen replay),
    to hold frozen renders against; skips under the scalar variant, which freezes nothing."""
    if engine.variant == SCALAR_VARIANT:
        pytest.skip("the scalar variant has nothing to freeze")
    traced = RenderEngine(engine.variant, freeze=False)
    traced.start()
    yield traced
    traced.close()
