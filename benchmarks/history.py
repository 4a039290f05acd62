"""Resending a search's history to the optimizer: prints bytes and ms per request at k views.

What resending the whole history to the stateless optimizer costs, against a step's work.

Run: ``.venv/bin/python -m benchmarks.history [--scene demo] [--views 40] [--reps 40]``

The optimizer keeps nothing between calls, so the controller sends every ``/next-pose`` request
with the target and *all* visited views and their detections; a search's k-th request carries k
views, and the search's total is quadratic in its length. This measures what that costs at
k = 1, 10, 20, 40 with the ``simple`` strategy, whose searches are the longest.

The history is a real one: a ``simple`` search by the controller's own search loop over
renderer, detector and optimizer processes on loopback (the target on the lowest ring, the
start on the highest, half way round; the scene's own detector when it has one), whose every
``/next-pose`` request is recorded. If the search ends before ``--views`` views, its last
request is extended with views of further grid poses, rendered and detected the same way (said
in the output).

Per k, medians over ``--reps`` rounds (the ks interleaved within a round, and one render +
detect per round, so the machine's load falls on all alike):

* ``bytes``: the request body;
* ``build``, ``encode``: the controller making the request from its views (as the search loop
  does) and serialising it (as :meth:`Stages.optimize` does);
* ``call``: the round trip through the broker to the real optimizer process;
* ``json``, ``plan``: in this process, what the optimizer does with the body: pydantic-core
  validates it straight from the bytes (``model_validate_json``, as the route does:
  :mod:`services.optimizer.json_body`), then :func:`~services.optimizer.planning.next_pose`
  runs with its caches warm (in a search every image but the newest view is found again in
  its image and view-mapping caches; here the scoring of the reference view is cached too,
  which does not grow with k);
* ``parse``: what FastAPI's body parameter paid for the same body (``json.loads`` and
  validation of the Python objects), the route's cost before it read the raw body;
* ``extra``: build + encode + call at k minus the same at k = 1, the cost of the resent views;
* ``step``: render + detect + build + encode + call, one iteration of the search loop;
* ``share``: extra / step.

The last line adds ``extra`` up over a search of ``--views`` views (linear between the
measured ks) against the search's summed steps.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import uvloop

from benchmarks.local import Controller, StageUrls, stage_processes
from cosmos.bench.runner import TARGET_SPP
from cosmos.bench.target import Target
from services.common.contracts.optimize import (
    NextPoseRequest,
    NextPoseResponse,
    VisitedView,
    searchable_grid,
)
from services.common.contracts.render import RenderRequest
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.pose import GridIndex, PoseQuery
from services.common.geometry.sphere import angular_distance_deg
from services.common.images import media_type_of
from services.controller.broker import Broker
from services.controller.stages import Stages
from services.controller.transport import StageRequest
from services.optimizer.planning import next_pose
from services.optimizer.settings import OptimizerSettings
from services.optimizer.wiring import build_optimizer
from services.renderer.client import RendererClient

STEPS = (1, 10, 20, 40)


class RecordingStages(Stages):
    """The controller's stage calls, keeping every ``/next-pose`` request the search makes."""

    def __init__(self, broker: Broker, **kw: Any) -> None:
        super().__init__(broker, **kw)
        self.requests: list[NextPoseRequest] = []

    async def optimize(self, request: NextPoseRequest, request_id: str = "") -> NextPoseResponse:
        self.requests.append(request)
        return await super().optimize(request, request_id)


def farthest_pair(grid: HemisphereGrid) -> tuple[GridIndex, GridIndex]:
    """A target on the lowest ring and the start on the highest, half way round: the simple
    search walks every ring and then half the widest one."""
    target = GridIndex(lat=grid.ring_count - 1, lon=0)
    start = GridIndex(lat=0, lon=grid.ring_size(0) // 2)
    return target, start


async def extended(
    stages: Stages, scene: str, request: NextPoseRequest, views: int
) -> NextPoseRequest:
    """``request`` with views of further grid poses (in grid order) up to ``views`` views."""
    grid = searchable_grid((await stages.scene(scene)).spec.search).grid()
    seen = {(v.pose.lat, v.pose.lon) for v in request.history}
    history = list(request.history)
    for flat in range(grid.size):
        if len(history) >= views:
            break
        index = grid.unflat(flat)
        if (index.lat, index.lon) in seen:
            continue
        image = await stages.render(scene, index)
        found = await stages.detect(image, media_type_of(image), scene=scene)
        history.append(
            VisitedView(
                pose=PoseQuery(lat=index.lat, lon=index.lon),
                image_size=found.image_size,
                detections=found.detections,
            )
        )
    return request.model_copy(update={"history": tuple(history)})


def build(request: NextPoseRequest, k: int) -> NextPoseRequest:
    """The request of the search's k-th view, made as the search loop makes it: a new
    :class:`VisitedView` per view, then the request."""
    visited = [
        VisitedView(pose=v.pose, image_size=v.image_size, detections=v.detections)
        for v in request.history[:k]
    ]
    fields = {name: getattr(request, name) for name in request.model_fields_set - {"history"}}
    return NextPoseRequest(**fields, history=tuple(visited))


def ms_since(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000


async def measure(
    urls: StageUrls, stages: Stages, scene: str, full: NextPoseRequest, reps: int
) -> dict[str, dict[int, list[float]]]:
    """Per quantity and k, the samples (module docstring); render and detect under k = 0."""
    context = build_optimizer(OptimizerSettings())
    steps = [k for k in STEPS if k <= len(full.history)]
    names = ("bytes", "build", "encode", "call", "parse", "plan", "json")
    out: dict[str, dict[int, list[float]]] = {name: {k: [] for k in steps} for name in names}
    out["render"], out["detect"] = {0: []}, {0: []}
    for k in steps:  # every view mapped once: the optimizer's view cache warm, as in a search
        warm = build(full, k).model_dump_json(exclude_none=True)
        next_pose(NextPoseRequest.model_validate_json(warm), context)
        await stages.broker.call("optimizer", "optimize", StageRequest.json("/next-pose", warm, {}))
    indices = [v.pose.as_index() for v in full.history]
    for rep in range(reps):
        index = indices[rep % len(indices)]
        if index is None:  # the search loop sends grid indices
            raise ValueError("a visited view without grid indices")
        t0 = time.perf_counter()
        image = await stages.render(scene, index)
        out["render"][0].append(ms_since(t0))
        t0 = time.perf_counter()
        await stages.detect(image, media_type_of(image), scene=scene)
        out["detect"][0].append(ms_since(t0))
        for k in steps if rep % 2 == 0 else reversed(steps):
            t0 = time.perf_counter()
            request = build(full, k)
            out["build"][k].append(ms_since(t0))
            t0 = time.perf_counter()
            body = request.model_dump_json(exclude_none=True).encode()
            out["encode"][k].append(ms_since(t0))
            out["bytes"][k].append(len(body))
            call = StageRequest.json("/next-pose", body, {})
            t0 = time.perf_counter()
            answer = await stages.broker.call("optimizer", "optimize", call)
            out["call"][k].append(ms_since(t0))
            if answer.status_code != 200:
                raise RuntimeError(f"/next-pose answered {answer.status_code}: {answer.text}")
            t0 = time.perf_counter()
            parsed = NextPoseRequest.model_validate(json.loads(body))
            out["parse"][k].append(ms_since(t0))
            t0 = time.perf_counter()
            next_pose(parsed, context)
            out["plan"][k].append(ms_since(t0))
            t0 = time.perf_counter()
            NextPoseRequest.model_validate_json(body)
            out["json"][k].append(ms_since(t0))
    return out


def report(samples: dict[str, dict[int, list[float]]], views: int) -> None:
    med = {name: {k: statistics.median(v) for k, v in per.items()} for name, per in samples.items()}
    render, detect = med["render"][0], med["detect"][0]
    steps = sorted(med["bytes"])
    controller = {k: med["build"][k] + med["encode"][k] + med["call"][k] for k in steps}
    base = controller[steps[0]]
    print(f"render {render:.1f} ms + detect {detect:.1f} ms per view (medians)")
    print(
        f"{'views':>5} {'bytes':>7} {'build':>6} {'encode':>6} {'call':>6} | {'parse':>6} "
        f"{'json':>6} {'plan':>6} | {'extra':>6} {'step':>6} {'share':>6}   (ms)"
    )
    for k in steps:
        extra = controller[k] - base
        step = render + detect + controller[k]
        print(
            f"{k:5d} {med['bytes'][k]:7.0f} {med['build'][k]:6.2f} {med['encode'][k]:6.2f} "
            f"{med['call'][k]:6.2f} | {med['parse'][k]:6.2f} {med['json'][k]:6.2f} "
            f"{med['plan'][k]:6.2f} | "
            f"{extra:6.2f} {step:6.1f} {extra / step:6.1%}"
        )
    ks = np.arange(1, views + 1)
    extra_k = np.interp(ks, steps, [controller[k] - base for k in steps])
    step_k = render + detect + np.interp(ks, steps, [controller[k] for k in steps])
    print(
        f"a {views}-view search: {extra_k.sum():.0f} ms of resent views in "
        f"{step_k.sum():.0f} ms of steps ({extra_k.sum() / step_k.sum():.1%})"
    )


async def run(args: argparse.Namespace, urls: StageUrls, workdir: Path) -> None:
    with RendererClient(urls.renderer, token=urls.token) as renderer:
        grid = searchable_grid(renderer.scene(args.scene).spec.search).grid()
        truth, start = farthest_pair(grid)
        render = RenderRequest(
            scene=args.scene, pose=PoseQuery(lat=truth.lat, lon=truth.lon), spp=TARGET_SPP
        )
        image = await asyncio.to_thread(renderer.render_png, render)
    begin, end = grid.pose(start), grid.pose(truth)
    apart = float(angular_distance_deg((begin.theta_deg, begin.phi_deg), end))
    target = Target(args.scene, image, truth, end)
    controller = Controller(urls, None, workdir / "history.sqlite3", RecordingStages)
    await controller.start()
    try:
        stages = controller.stages
        if not isinstance(stages, RecordingStages):
            raise TypeError("the controller must record its requests")
        await controller.search(target, "simple", start=begin, seed=0)
        searched = len(stages.requests[-1].history)
        full = await extended(stages, args.scene, stages.requests[-1], args.views)
        added = len(full.history) - searched
        print(
            f"{args.scene}: a simple search from {apart:.0f}° away took {searched} views"
            + (f"; {added} more grid poses added to the history" if added else "")
        )
        samples = await measure(urls, stages, args.scene, full, args.reps)
    finally:
        await controller.close()
    report(samples, args.views)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--views", type=int, default=max(STEPS), help="history length")
    parser.add_argument("--reps", type=int, default=40, help="rounds")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp, stage_processes(Path(tmp)) as urls:
        uvloop.run(run(args, urls, Path(tmp)))


if __name__ == "__main__":
    main()
