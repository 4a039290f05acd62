"""``cosmos demo``: the whole thing end to end on the demo scene: starts the stack on free ports,
renders a target from a random grid pose, searches for it, prints the true and found poses."""

from __future__ import annotations

import argparse
import random
import tempfile
import time
from pathlib import Path

from cosmos.cli.common import Commands
from cosmos.cli.follow import follow
from cosmos.stack import local_stack
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import PoseQuery
from services.controller.client import (
    ControllerClient,
)
from services.renderer.client import RendererClient

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    """Start the stack on free ports, render a target from a random grid pose, search for it."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get("demo")
    grid = scene.spec.search.grid()
    rng = random.Random(args.seed)
    index = grid.unflat(rng.randrange(grid.size))
    pose = grid.pose(index)
    print(f"demo scene: {len(scene.spec.objects)} objects, {grid.size} grid poses")
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        with local_stack(Path(tmp)) as stack:
            print(
                f"stack up in {time.perf_counter() - started:.1f} s (controller {stack.controller})"
            )
            with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
                target = renderer.render_png(
                    RenderRequest(scene="demo", pose=PoseQuery(lat=index.lat, lon=index.lon))
                )
            (out / "demo-target.png").write_bytes(target)
            print(
                f"target rendered at lat {index.lat}, lon {index.lon} "
                f"(θ {pose.theta_deg:.1f}°, φ {pose.phi_deg:.1f}°): {out / 'demo-target.png'}"
            )
            with ControllerClient(stack.controller, api_key=stack.api_key) as client:
                search = client.submit(target, "demo", seed=rng.randrange(2**31))
                print(
                    f"searching with {search.strategy} from lat {search.start.index.lat}, "
                    f"lon {search.start.index.lon}"
                )
                final = follow(client, search, out)
    found = final.result
    print(
        f"true pose:  lat {index.lat:>2}, lon {index.lon:>2} "
        f"(θ {pose.theta_deg:.1f}°, φ {pose.phi_deg:.1f}°)"
    )
    if found is not None:
        print(
            f"found pose: lat {found.pose.index.lat:>2}, lon {found.pose.index.lon:>2} "
            f"(θ {found.pose.theta_deg:.1f}°, φ {found.pose.phi_deg:.1f}°) "
            f"after {found.renders} renders"
        )
    print(f"total {time.perf_counter() - started:.1f} s")
    ok = found is not None and found.pose.index == index
    print("the search found the target's grid pose" if ok else "the search did NOT find the target")
    return 0 if ok else 3


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    demo = commands.add_parser("demo", help="a whole search on the demo scene, end to end")
    demo.add_argument("--out", default="out")
    demo.add_argument("--seed", type=int, help="seed of the random target and start poses")
    demo.set_defaults(run=run)
