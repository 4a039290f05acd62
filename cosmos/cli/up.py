"""``cosmos up``: the four services as local processes, each started again if it exits (Ctrl-C
or SIGTERM stops them all), and the local API key, printed and kept beside the controller's
database (``data/api-key``)."""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

from cosmos.cli.common import Commands, local_database_url, say
from cosmos.stack import plan_stack, running_stack
from services.common.auth import TOKEN_VARIABLE, token_from_environment
from services.controller.keys import key_file, local_key

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    from cosmos.environment import report_unknown_variables

    report_unknown_variables()  # each service warns too, but into its log file
    database_url = local_database_url(args.database_url)
    try:
        api_key: str | None = local_key(database_url)
        where = f"kept in {key_file(database_url)}, which cosmos search reads"
    except ValueError as exc:  # an in-memory database: no other process can add a key
        api_key, where = None, str(exc)
    plan = plan_stack(
        host=args.host,
        controller_port=args.port,
        renderer_port=args.port + 1,
        detector_port=args.port + 2,
        optimizer_port=args.port + 3,
        renderers=args.renderers,
        detectors=args.detectors,
        database_url=database_url,
        service_token=token_from_environment(),  # else one for this run
    )
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    with running_stack(
        plan, Path(args.logs), host=args.host, api_key=api_key, supervise=True, say=say
    ) as stack:
        print(f"controller  {stack.controller}")
        print(f"page        {stack.controller}/ (open it in a browser; it asks for the key once)")
        print(f"API key     {stack.api_key or 'none'} (admin; {where})")
        for name, urls in (
            ("renderer", stack.renderers),
            ("detector", stack.detectors),
            ("optimizer", stack.optimizers),
        ):
            print(f"{name:<11} {', '.join(urls)}")
        if token_from_environment() is None:
            print(
                "the stages serve only the controller (a new service token for this run; set "
                f"{TOKEN_VARIABLE} before cosmos up to call them yourself)"
            )
        print(
            f"logs in {args.logs}; a service that exits is started again; Ctrl-C stops everything",
            flush=True,
        )
        while not stop.wait(1.0):
            pass
    print("stopped")
    return 0


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    up = commands.add_parser("up", help="run the four services as local processes")
    up.add_argument("--host", default="127.0.0.1")
    up.add_argument(
        "--port", type=int, default=8000, help="controller port; stages use the next three"
    )
    up.add_argument("--renderers", type=int, default=1)
    up.add_argument("--detectors", type=int, default=1)
    up.add_argument("--database-url", help="the controller's COSMOS_CONTROLLER_DATABASE_URL")
    up.add_argument("--logs", default="logs", help="folder for the services' logs")
    up.set_defaults(run=run)
