"""The optimizer's fixtures: a real optimizer process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cosmos.launch import ServiceProcess, running_service


@pytest.fixture(scope="module")
def optimizer_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A real optimizer with small caps, so fuzzing stays fast."""
    logs: Path = tmp_path_factory.mktemp("logs")
    env = {
        "COSMOS_OPTIMIZER_MAX_GRID_POSES": "1500",
        "COSMOS_OPTIMIZER_MAX_HISTORY_DETECTIONS": "300",
    }
    with running_service("services.optimizer.app:app", logs, env) as service:
        yield service
