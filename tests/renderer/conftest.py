"""The renderer's fixtures: a real renderer process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cosmos.launch import ServiceProcess, running_service


@pytest.fixture(scope="session")
def renderer_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A real renderer (uvicorn) on loopback with small caps, so fuzzing stays fast."""
    logs: Path = tmp_path_factory.mktemp("logs")
    env = {"COSMOS_RENDERER_MAX_SIDE": "640", "COSMOS_RENDERER_MAX_SAMPLES": str(640 * 480 * 16)}
    with running_service("services.renderer.app:app", logs, env) as service:
        yield service
