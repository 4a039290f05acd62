"""What several commands share: the controller database and key a local command means, the
timestamped line a long-running command says on stderr, and comma lists that start with a minus
sign."""

from __future__ import annotations

import argparse
import re
import sys
import time
from typing import TypeAlias

from cosmos.launch import ROOT
from services.controller.keys import client_key, rooted

__all__ = ["Commands", "accept_negative_lists", "client_api_key", "local_database_url", "say"]


def local_database_url(given: str | None = None) -> str:
    """The controller database a local command means: ``given``, else the controller's own
    setting (``COSMOS_CONTROLLER_DATABASE_URL`` or its default); a relative path is taken from
    the repository root, where ``cosmos up`` runs the services."""
    from services.controller.settings import ControllerSettings

    return rooted(given or ControllerSettings().controller_database_url, ROOT)


def client_api_key() -> str | None:
    """``COSMOS_API_KEY``, else the local key ``cosmos up`` keeps (None: none found)."""
    return client_key(local_database_url())


def accept_negative_lists(parser: argparse.ArgumentParser) -> None:
    """Let ``parser`` take a value such as ``-0.12,0.03,0,0`` (a barrel lens's distortion) or
    ``-3,0,2`` (a position): argparse takes it for a flag, because only a lone number counts as
    negative. None of the commands' flags starts with a digit, so ``-digit`` or ``-.digit``
    always begins a value."""
    parser._negative_number_matcher = re.compile(r"^-\.?\d")


def say(message: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} cosmos: {message}", file=sys.stderr, flush=True)


Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"
"""What the command modules add their parsers to."""
