"""``cosmos scenes [--url URL]``: the scenes (local files, or a running renderer); ``cosmos
scenes add PATH`` is :mod:`cosmos.cli.onboard`."""

from __future__ import annotations

import argparse

from cosmos.cli.common import Commands
from cosmos.cli.onboard import ONBOARD_HELP, add_arguments
from services.common.auth import token_from_environment
from services.common.catalog import SceneCatalog
from services.renderer.client import RendererClient
from services.renderer.settings import RendererSettings

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    if args.url:
        with RendererClient(args.url, token=token_from_environment()) as client:
            for summary in client.scenes():
                print(
                    f"{summary.id:<16} {summary.objects:>3} objects  {summary.grid_size:>5} poses"
                )
        return 0
    catalog = SceneCatalog(RendererSettings().scene_directories())
    for scene_id in catalog.ids():
        scene = catalog.get(scene_id)
        print(
            f"{scene_id:<16} {len(scene.spec.objects):>3} objects  "
            f"{scene.spec.search.grid().size:>5} poses  {scene.path}"
        )
    for scene_id, error in catalog.invalid().items():
        print(f"{scene_id:<16} INVALID: {error}")
    return 0


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    scenes = commands.add_parser("scenes", help="list the scenes, or add one (train its detector)")
    scenes.add_argument("--url", help="ask a running renderer instead of reading the files")
    scenes.set_defaults(run=run)
    scene_commands = scenes.add_subparsers(dest="scenes_command")
    add_arguments(scene_commands.add_parser("add", help=ONBOARD_HELP))
