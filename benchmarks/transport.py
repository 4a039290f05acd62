"""The controller's two stage transports, side by side: stage calls and whole searches.

Run: ``.venv/bin/python -m benchmarks.transport [--calls 200] [--searches 60] [--pause-ms 40]``

Renderer, detector and optimizer run as real uvicorn processes on loopback; the controller's
side runs in this process on uvloop, as uvicorn runs the controller. Both transports talk to the
same processes, each over its own kept-alive connections, and every measurement alternates
between them (A B, then B A), so the machine's load falls on both alike.

*Stage calls*: a search's detect and plan calls. Each round waits ``--pause-ms`` (the controller
and the replicas idle, as while a view renders), then sends the detector a 320x240 PPM view of
the demo scene, then the optimizer the ``/next-pose`` request of a search three views in.
*Searches*: ``--searches`` targets of the demo scene (rendered at the bench's 16 spp from seeded
grid poses and starts), each searched once per transport by the controller's own search loop
(:class:`~services.controller.runner.SearchRunner` over a :class:`Broker` given that transport);
the time runs from the submission (:func:`~services.controller.submit.create_search`) to the
search's end, everything but the upload to the controller's API.

Printed: medians, means and p90 per transport; B/A of the medians and the mean paired
difference B − A (same round, same target) with its standard error; for the searches also the
stage calls per search, so that a per-call difference can be set against the per-search one.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import uvloop

from benchmarks.local import SCENE, Controller, StageUrls, Target, make_targets, stage_processes
from services.common.models import PoseQuery
from services.common.optimization import (
    NextPoseRequest,
    StrategyName,
    TargetImage,
    VisitedView,
    search_grid,
)
from services.controller.broker import Broker
from services.controller.http1 import Http1Transport
from services.controller.stages import Stages
from services.controller.transport import AiohttpTransport, StageRequest, Transport


def summary(samples: Sequence[float]) -> str:
    """Median, mean and p90 in milliseconds."""
    values = np.asarray(samples)
    return (
        f"median {np.median(values):7.2f}  mean {values.mean():7.2f}  "
        f"p90 {np.percentile(values, 90):7.2f} ms"
    )


def ratio(b: Sequence[float], a: Sequence[float]) -> str:
    """B/A of the medians, and the mean of the paired differences B − A with its standard
    error."""
    paired = np.asarray(b) - np.asarray(a)
    error = paired.std(ddof=1) / np.sqrt(len(paired))
    return (
        f"B/A {statistics.median(b) / statistics.median(a):.3f}  "
        f"(paired B − A {paired.mean():+.2f} ± {error:.2f} ms)"
    )


def in_turn(round_number: int, kinds: Sequence[str]) -> list[str]:
    """A B, then B A, ...: each transport goes first every other round."""
    return list(kinds) if round_number % 2 == 0 else list(reversed(kinds))


def make_transports() -> dict[str, Transport]:
    """The transports compared, A and B."""
    return {
        "A Http1Transport": Http1Transport(connect_timeout_s=2.0),
        "B AiohttpTransport": AiohttpTransport(connect_timeout_s=2.0),
    }


async def stage_calls(
    urls: StageUrls, transports: dict[str, Transport], calls: int, pause_s: float
) -> None:
    """Detect and plan calls through each transport, interleaved (module docstring)."""
    stages = Stages(Broker(urls.pools(), transport=next(iter(transports.values()))), render_spp=8)
    scene = await stages.scene(SCENE)
    grid = search_grid(scene.spec.search)
    flat = grid.grid()
    poses = [flat.unflat(i) for i in (0, flat.size // 3, flat.size // 2, 2 * flat.size // 3)]
    views = [await stages.render(SCENE, index) for index in poses]
    found = [await stages.detect(view, "image/x-portable-pixmap", scene=SCENE) for view in views]
    request = NextPoseRequest(
        strategy="reprojection",
        camera=scene.spec.camera,
        grid=grid,
        target=TargetImage(image_size=found[0].image_size, detections=found[0].detections),
        history=tuple(
            VisitedView(
                pose=PoseQuery(lat=index.lat, lon=index.lon),
                image_size=answer.image_size,
                detections=answer.detections,
            )
            for index, answer in zip(poses[1:], found[1:], strict=True)
        ),
    )
    plan_body = request.model_dump_json(exclude_none=True).encode()
    detect = StageRequest(
        "POST", f"/detect?scene={SCENE}", views[1], {"Content-Type": "image/x-portable-pixmap"}
    )
    plan = StageRequest.json("/next-pose", plan_body, {})
    print(
        f"stage calls: {calls} rounds, {pause_s * 1000:.0f} ms idle before each; detect body "
        f"{len(views[1])} B, /next-pose body {len(plan_body)} B"
    )
    names = list(transports)
    took: dict[str, dict[str, list[float]]] = {n: {"detect": [], "plan": []} for n in names}
    for _ in range(3):  # connections made and code paths warm before anything counts
        for name in names:
            await transports[name].send(urls.detector, detect, 30.0)
            await transports[name].send(urls.optimizer, plan, 30.0)
    for round_number in range(calls):
        for name in in_turn(round_number, names):
            transport = transports[name]
            await asyncio.sleep(pause_s)
            t0 = time.perf_counter()
            answer = await transport.send(urls.detector, detect, 30.0)
            t1 = time.perf_counter()
            planned = await transport.send(urls.optimizer, plan, 30.0)
            t2 = time.perf_counter()
            if answer.status_code != 200 or planned.status_code != 200:
                raise RuntimeError(f"{name}: {answer.status_code} / {planned.status_code}")
            took[name]["detect"].append((t1 - t0) * 1000)
            took[name]["plan"].append((t2 - t1) * 1000)
    for call in ("detect", "plan"):
        for name in names:
            print(f"  {call:7s} {name:22s} {summary(took[name][call])}")
        if len(names) == 2:
            print(f"  {call:7s} {'':22s} {ratio(took[names[1]][call], took[names[0]][call])}")


async def searches(
    urls: StageUrls,
    transports: dict[str, Transport],
    targets: Sequence[Target],
    strategy: StrategyName,
    workdir: Path,
) -> None:
    """Every target searched once through each transport, interleaved (module docstring)."""
    names = list(transports)
    controllers = {
        name: Controller(urls, transports[name], workdir / f"controller-{i}.sqlite3")
        for i, name in enumerate(names)
    }
    for controller in controllers.values():
        await controller.start()
    walls: dict[str, list[float]] = {name: [] for name in names}
    calls: dict[str, list[int]] = {name: [] for name in names}
    try:
        for name in names:  # scenes cached, connections made, code paths warm
            await controllers[name].search(targets[0], strategy)
        for round_number, target in enumerate(targets):
            for name in in_turn(round_number, names):
                wall_ms, count = await controllers[name].search(target, strategy)
                walls[name].append(wall_ms)
                calls[name].append(count)
    finally:
        for controller in controllers.values():
            await controller.close()
    print(f"searches: {len(targets)} demo targets, strategy {strategy}")
    for name in names:
        print(
            f"  search  {name:22s} {summary(walls[name])}  "
            f"({statistics.mean(calls[name]):.1f} stage calls per search)"
        )
    if len(names) == 2:
        print(f"  search  {'':22s} {ratio(walls[names[1]], walls[names[0]])}")


async def run(
    args: argparse.Namespace, urls: StageUrls, targets: list[Target], workdir: Path
) -> None:
    transports = make_transports()
    try:
        await stage_calls(urls, transports, args.calls, args.pause_ms / 1000)
        await searches(urls, transports, targets, args.strategy, workdir)
    finally:
        for transport in transports.values():
            await transport.close()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=200, help="rounds of stage calls")
    parser.add_argument("--searches", type=int, default=60, help="targets, each searched twice")
    parser.add_argument("--pause-ms", type=float, default=40.0, help="idle time before a call")
    parser.add_argument("--strategy", default="reprojection", help="the searches' strategy")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp, stage_processes(Path(tmp)) as urls:
        targets = make_targets(urls.renderer, args.searches, args.seed)
        uvloop.run(run(args, urls, targets, Path(tmp)))


if __name__ == "__main__":
    main()
