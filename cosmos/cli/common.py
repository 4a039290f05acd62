"""What several commands share: the controller database and key a local command means, and
the timestamped line a long-running command says on stderr."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TypeAlias

from cosmos.launch import ROOT
from services.controller.keys import client_key, rooted

__all__ = ["Commands", "client_api_key", "local_database_url", "say"]


def local_database_url(given: str | None = None) -> str:
    """The controller database a local command means: ``given``, else the controller's own
    setting (``COSMOS_CONTROLLER_DATABASE_URL`` or its default); a relative path is taken from
    the repository root, where ``cosmos up`` runs the services."""
    from services.controller.settings import ControllerSettings

    return rooted(given or ControllerSettings().controller_database_url, ROOT)


def client_api_key() -> str | None:
    """``COSMOS_API_KEY``, else the local key ``cosmos up`` keeps (None: none found)."""
    return client_key(local_database_url())


def say(message: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} cosmos: {message}", file=sys.stderr, flush=True)


Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"
"""What the command modules add their parsers to."""
