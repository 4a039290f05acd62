"""The ``cosmos`` command: one module per command, wired here.

* ``cosmos scenes [--url URL]``: the scenes (:mod:`.scenes`);
* ``cosmos scenes add PATH`` (or ``cosmos onboard PATH``): train, measure and install the scene's
  own detector beside its file (:mod:`.onboard`, :mod:`training.onboard`; needs the ``train``
  extra);
* ``cosmos render``: one view, in this process or by a running renderer (:mod:`.render`);
* ``cosmos up``: the four services as local processes, and the local API key (:mod:`.up`);
* ``cosmos search target.png --scene demo``: submit a search, follow it, save its plots
  (:mod:`.search`, :mod:`.follow`);
* ``cosmos keys create|list|revoke``: the controller's API keys (:mod:`.keys`);
* ``cosmos demo``: the whole thing end to end on the demo scene (:mod:`.demo`);
* ``cosmos bench``: the paper's evaluation through the real services (:mod:`.bench`,
  :mod:`cosmos.bench`).

The commands that call a running controller (``search``, ``bench --url``) send the key in
``COSMOS_API_KEY``, else the one ``cosmos up`` keeps beside the controller's database; ``demo``
and ``bench`` without ``--url`` start their own stack, with its own key.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import httpx

from cosmos.cli import bench, demo, keys, onboard, render, scenes, search, up
from services.common.errors import ServiceError
from services.controller.client import ControllerError
from services.renderer.client import RendererError

__all__ = ["main", "unreachable"]

COMMANDS = (scenes, onboard, render, demo, up, keys, search, bench)
"""The command modules, in the order ``cosmos --help`` lists them."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cosmos", description="COSMOS 3D Search")
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.register(commands)
    return parser


def unreachable(exc: httpx.TransportError) -> str:
    """What to tell a person whose command could not reach a service: which address, what
    went wrong, and how to get a stack there."""
    try:
        url = exc.request.url
        where = f"{url.scheme}://{url.netloc.decode()}"
    except RuntimeError:  # an error raised without its request
        where = "the service"
    if isinstance(exc, httpx.TimeoutException):
        what = "did not answer in time"
    else:
        what = f"cannot be reached ({exc or type(exc).__name__})"
    return (
        f"{where} {what}: start the services with `cosmos up` (or `cosmos demo` for a whole "
        "search in one command), or pass --url with the address of a running stack"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cosmos``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        status: int = args.run(args)
    except ServiceError as exc:
        print(f"cosmos: {exc.detail}", file=sys.stderr)
        return 2
    except (RendererError, ControllerError, RuntimeError, ValueError, OSError) as exc:
        print(f"cosmos: {exc}", file=sys.stderr)
        return 1
    except httpx.TransportError as exc:
        print(f"cosmos: {unreachable(exc)}", file=sys.stderr)
        return 1
    return status
