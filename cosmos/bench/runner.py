"""Running the evaluation's searches through the controller over HTTP, as a user's client would.

A bench run first renders every target (through a renderer, with its own seed and the
renderer's default sampling, so a target is never pixel-identical to a view the search renders),
then submits each (target, strategy) pair to ``POST /searches`` with the target's start pose
(or, for the predicted-start runs, without one: :func:`with_starts`),
follows the search's server-sent events until its ``end`` event and fetches the search. The wall
time of a search runs from sending the ``POST`` to receiving ``end``: everything a client waits
for. The client is aiohttp, as in the controller's own stage calls: httpx costs ~4 ms more per
search on the 230 KB upload alone (measured on the 2-core bench machine), which would be the
bench's cost, not the stack's. Every strategy gets the same targets and start poses, so
strategies are compared pairwise.

``photo`` and ``changed`` targets are rendered from a modified copy of the scene written by
:func:`cosmos.bench.altered.alter_scene` into a folder the renderer reads
(``COSMOS_SCENES_DIR``); their searches run in the original scene. Every search that misses its
target, or answers without confirming, carries a :class:`~cosmos.bench.traces.FailureTrace`.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any

import aiohttp
import numpy as np
from pydantic import Field

from cosmos.bench.altered import AlteredScene, alter_scene
from cosmos.bench.target import Target
from cosmos.bench.traces import FailureTrace, confirmed_of, failure_trace
from cosmos.bench.variants import SCENE_VARIANTS, VARIANTS, Variant, degrade, draw_pose
from cosmos.stack import Stack
from cosmos.stack import local_stack as services_stack
from services.common.base import FrozenModel
from services.common.contracts.optimize import StrategyName
from services.common.contracts.render import RenderRequest
from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.geometry.scene import LoadedScene
from services.common.geometry.sphere import angular_distance_deg
from services.common.images import media_type_of
from services.renderer.client import RendererClient

__all__ = [
    "IterationRecord",
    "SearchRecord",
    "SearchRefused",
    "BenchTarget",
    "local_stack",
    "make_targets",
    "post_and_follow",
    "run_searches",
    "with_starts",
]

TARGET_SPP = 16
"""Samples per pixel of the targets (the renderer's default): a user's image, not the bench's."""


@dataclass(frozen=True, kw_only=True)
class BenchTarget(Target):
    """A target of the evaluation: where its search starts, its seed, and where it came from."""

    start: GridIndex
    start_pose: Pose
    seed: int
    variant: Variant
    number: int
    rendered_scene: str | None = None
    """The modified copy the target was rendered from (``photo``, ``changed``)."""
    change: str = ""
    """What the copy changed, in words."""
    given_start: bool = True
    """Whether its search is given ``start`` (the paper's protocol), or none: the controller
    then starts at the pose it predicts from the target (``start`` only if it predicts none)."""

    @property
    def key(self) -> tuple[str, str, int]:
        return (self.scene, self.variant, self.number)


class SearchRefused(Exception):
    """The controller refused a submission (any answer but 202)."""


class IterationRecord(FrozenModel):
    """One rendered view of a bench search, with its angle to the true pose."""

    lat: int
    lon: int
    theta_deg: float
    phi_deg: float
    distance_deg: Annotated[float, Field(ge=0.0)]
    render_ms: float
    detect_ms: float
    optimize_ms: float
    total_ms: float


class SearchRecord(FrozenModel):
    """What one bench search did and how long it took (milliseconds)."""

    scene: str
    strategy: StrategyName
    variant: Variant
    number: int
    search_id: str | None
    status: str
    true_theta_deg: float
    true_phi_deg: float
    truth: GridIndex
    start: GridIndex
    found: GridIndex | None = None
    refined_theta_deg: float | None = None
    refined_phi_deg: float | None = None
    success: bool = False
    refined_error_deg: float | None = Field(
        default=None, description="Angle between the true view direction and refined_pose."
    )
    renders: int = 0
    after_renders: int = Field(
        default=0, description="Renders after the iterations (their edges settle the answer)."
    )
    iterations: int = 0
    wall_ms: float = 0.0
    render_ms: float = 0.0
    detect_ms: float = 0.0
    optimize_ms: float = 0.0
    loop_ms: float = Field(default=0.0, description="Sum of the iterations' total_ms.")
    error: str | None = None
    trajectory: tuple[IterationRecord, ...] = ()
    arm: str = Field(
        default="general", description="The detector model: general, or the scene's own."
    )
    confirmed: bool | None = Field(
        default=None, description="The result's confirmed flag (None without a result)."
    )
    change: str = ""
    trace: FailureTrace | None = None
    start_given: bool = Field(
        default=True,
        description="Whether the search was given its start (else the controller predicted it).",
    )

    @property
    def found_truth(self) -> bool:
        """The search answered the true grid pose, confirmed or not."""
        return self.found is not None and self.found == self.truth

    @property
    def moves(self) -> int:
        """Moves after the start view (the paper's steps): iterations − 1."""
        return max(0, self.iterations - 1)

    @property
    def stage_ms(self) -> float:
        return self.render_ms + self.detect_ms + self.optimize_ms

    @property
    def other_ms(self) -> float:
        """HTTP and queueing: the wall time not spent in a render, detection or optimizer call."""
        return max(0.0, self.wall_ms - self.stage_ms)


def with_starts(targets: Sequence[BenchTarget], starts: Sequence[str]) -> list[BenchTarget]:
    """Each target once per start mode: ``given`` (its drawn start, the paper's protocol) and
    ``predicted`` (no start given: the controller predicts it from the target)."""
    return [
        target if start == "given" else replace(target, given_start=False)
        for start in starts
        for target in targets
    ]


def _rng(seed: int, scene: str, variant: Variant) -> np.random.Generator:
    """One independent stream per (seed, scene, variant): adding a scene changes no other's."""
    return np.random.default_rng([seed, zlib.crc32(scene.encode()), VARIANTS.index(variant)])


def make_targets(
    renderer_url: str,
    scenes: Sequence[str],
    variants: Sequence[Variant],
    n: int,
    seed: int,
    progress: Callable[[str], None] | None = None,
    *,
    scene_of: Callable[[str], LoadedScene] | None = None,
    altered_dir: Path | None = None,
    token: str | None = None,
) -> list[BenchTarget]:
    """``n`` seeded targets per scene and variant, rendered by the renderer at ``renderer_url``
    (``token``: the stack's service token).

    ``photo`` and ``changed`` targets need ``scene_of`` (a scene by id, to copy) and
    ``altered_dir``, a folder that renderer reads scenes from.
    """

    def copy_of(
        scene: str, variant: Variant, rng: np.random.Generator, number: int
    ) -> AlteredScene:
        if scene_of is None or altered_dir is None:
            raise ValueError(
                "photo and changed targets are rendered from copies of the scene that the "
                "renderer must read: run them on a local stack (without --url)"
            )
        return alter_scene(scene_of(scene), variant, rng, altered_dir, f"{scene}_{variant}{number}")

    targets: list[BenchTarget] = []
    with RendererClient(renderer_url, token=token) as renderer:
        for scene in scenes:
            grid = renderer.scene(scene).grid.grid()
            for variant in variants:
                rng = _rng(seed, scene, variant)
                for number in range(n):
                    where = draw_pose(grid, variant, rng)
                    start = grid.unflat(int(rng.integers(grid.size)))
                    render_seed, search_seed = (int(v) for v in rng.integers(2**31, size=2))
                    rendered, change = scene, ""
                    if variant in SCENE_VARIANTS:
                        copy = copy_of(scene, variant, rng, number)
                        rendered, change = copy.id, copy.change
                    query = (
                        PoseQuery(lat=where.truth.lat, lon=where.truth.lon)
                        if where.on_grid
                        else PoseQuery(theta_deg=where.pose.theta_deg, phi_deg=where.pose.phi_deg)
                    )
                    png = renderer.render_png(
                        RenderRequest(scene=rendered, pose=query, spp=TARGET_SPP, seed=render_seed)
                    )
                    targets.append(
                        BenchTarget(
                            scene=scene,
                            variant=variant,
                            number=number,
                            pose=where.pose,
                            truth=where.truth,
                            start=start,
                            start_pose=grid.pose(start),
                            seed=search_seed,
                            image=degrade(png, variant, rng),
                            rendered_scene=rendered if rendered != scene else None,
                            change=change,
                        )
                    )
                if progress is not None:
                    progress(f"rendered {n} {variant} targets of {scene}")
    return targets


def record_of(
    target: BenchTarget,
    strategy: StrategyName,
    search: Search,
    wall_ms: float,
    raw: Mapping[str, Any] | None = None,
    arm: str = "general",
) -> SearchRecord:
    """The bench's view of a finished search: success against the ground truth, stage times
    (with a render after the iterations and its refinement, in render and optimize ms);
    from ``raw`` (the search's JSON) whether its answer was confirmed, and the trace of a miss or
    an unconfirmed answer."""
    raw = raw if raw is not None else search.model_dump(mode="json")
    confirmed = confirmed_of(raw)
    trajectory = tuple(
        IterationRecord(
            lat=it.pose.index.lat,
            lon=it.pose.index.lon,
            theta_deg=it.pose.theta_deg,
            phi_deg=it.pose.phi_deg,
            distance_deg=float(
                angular_distance_deg((it.pose.theta_deg, it.pose.phi_deg), target.pose)
            ),
            render_ms=it.timings.render_ms,
            detect_ms=it.timings.detect_ms,
            optimize_ms=it.timings.optimize_ms,
            total_ms=it.timings.total_ms,
        )
        for it in search.iterations
    )
    result = search.result
    after = result.refit_timings if result is not None else None
    found, refined = (result.pose.index, result.refined_pose) if result else (None, None)
    success = search.status == "succeeded" and found == target.truth
    return SearchRecord(
        scene=target.scene,
        strategy=strategy,
        variant=target.variant,
        number=target.number,
        search_id=search.id,
        status=search.status,
        true_theta_deg=target.pose.theta_deg,
        true_phi_deg=target.pose.phi_deg,
        truth=target.truth,
        start=target.start,
        found=found,
        refined_theta_deg=refined.theta_deg if refined is not None else None,
        refined_phi_deg=refined.phi_deg if refined is not None else None,
        success=success,
        refined_error_deg=(
            float(angular_distance_deg(refined, target.pose)) if refined is not None else None
        ),
        renders=result.renders if result is not None else len({(t.lat, t.lon) for t in trajectory}),
        after_renders=int(after is not None),
        iterations=len(trajectory),
        wall_ms=wall_ms,
        render_ms=sum(t.render_ms for t in trajectory) + (after.render_ms if after else 0.0),
        detect_ms=sum(t.detect_ms for t in trajectory),
        optimize_ms=sum(t.optimize_ms for t in trajectory) + (after.refine_ms if after else 0.0),
        loop_ms=sum(t.total_ms for t in trajectory),
        error=search.error.detail if search.error is not None else None,
        trajectory=trajectory,
        arm=arm,
        confirmed=confirmed,
        change=target.change,
        trace=failure_trace(raw, target.truth) if not success or confirmed is False else None,
        start_given=target.given_start,
    )


def _failed(
    target: BenchTarget, strategy: StrategyName, detail: str, wall_ms: float, arm: str
) -> SearchRecord:
    return SearchRecord(
        scene=target.scene,
        strategy=strategy,
        variant=target.variant,
        number=target.number,
        search_id=None,
        status="error",
        true_theta_deg=target.pose.theta_deg,
        true_phi_deg=target.pose.phi_deg,
        truth=target.truth,
        start=target.start,
        wall_ms=wall_ms,
        error=detail,
        arm=arm,
        change=target.change,
        trace=FailureTrace(truth_visited=False, status="error", final_reason=detail),
        start_given=target.given_start,
    )


def _search_query(
    target: BenchTarget, strategy: StrategyName, max_iterations: int
) -> dict[str, str]:
    query = {
        "scene": target.scene,
        "strategy": strategy,
        "seed": str(target.seed),
        "max_iterations": str(max_iterations),
    }
    if target.given_start:
        query["start_theta_deg"] = repr(target.start_pose.theta_deg)
        query["start_phi_deg"] = repr(target.start_pose.phi_deg)
    return query


async def post_and_follow(
    http: aiohttp.ClientSession, base_url: str, image: bytes, query: Mapping[str, str]
) -> tuple[dict[str, Any], float]:
    """``POST /searches`` with ``image`` as the raw body and the options in the query (what a
    program sends: no multipart), follow its events to ``end`` and fetch it: the search's JSON
    and the wall time in ms from sending the ``POST`` to receiving ``end``. Raises
    :class:`SearchRefused` for any answer but 202, aiohttp's errors or :class:`TimeoutError`
    when the connection fails or a wait runs out."""
    headers = {"Content-Type": media_type_of(image)}
    started = time.perf_counter()
    async with http.post(f"{base_url}/searches", data=image, params=query, headers=headers) as r:
        body = await r.read()
        if r.status != 202:
            text = body[:300].decode(errors="replace")
            raise SearchRefused(f"POST /searches answered {r.status}: {text}")
    search_id = json.loads(body)["id"]
    async with http.get(f"{base_url}/searches/{search_id}/events") as events:
        events.raise_for_status()
        async for line in events.content:
            if line.rstrip(b"\r\n") == b"event: end":
                break
    wall_ms = (time.perf_counter() - started) * 1000
    async with http.get(f"{base_url}/searches/{search_id}") as final:
        final.raise_for_status()
        raw: dict[str, Any] = json.loads(await final.read())
    return raw, wall_ms


async def _one_search(
    http: aiohttp.ClientSession,
    base_url: str,
    target: BenchTarget,
    strategy: StrategyName,
    max_iterations: int,
    arm: str,
) -> SearchRecord:
    query = _search_query(target, strategy, max_iterations)
    started = time.perf_counter()
    try:
        raw, wall_ms = await post_and_follow(http, base_url, target.image, query)
        search = Search.model_validate(raw)
    except (SearchRefused, aiohttp.ClientError, TimeoutError) as exc:
        detail = str(exc) if isinstance(exc, SearchRefused) else f"{type(exc).__name__}: {exc}"
        return _failed(target, strategy, detail, (time.perf_counter() - started) * 1000, arm)
    return record_of(target, strategy, search, wall_ms, raw, arm)


async def _run(
    controller_url: str,
    jobs: Sequence[tuple[BenchTarget, StrategyName]],
    concurrency: int,
    max_iterations: int,
    progress: Callable[[int, SearchRecord], None] | None,
    timeout_s: float,
    arm: str,
    api_key: str | None,
) -> list[SearchRecord]:
    records: list[SearchRecord | None] = [None] * len(jobs)
    queue: asyncio.Queue[int] = asyncio.Queue()
    for i in range(len(jobs)):
        queue.put_nowait(i)
    done = 0
    base_url = controller_url.rstrip("/")
    connector = aiohttp.TCPConnector(limit=2 * concurrency + 4)
    timeout = aiohttp.ClientTimeout(total=timeout_s, connect=5.0)

    headers = {"Authorization": f"Bearer {api_key}"} if api_key is not None else None
    async with aiohttp.ClientSession(connector=connector, timeout=timeout, headers=headers) as http:

        async def worker() -> None:
            nonlocal done
            while not queue.empty():
                i = queue.get_nowait()
                target, strategy = jobs[i]
                record = await _one_search(http, base_url, target, strategy, max_iterations, arm)
                records[i] = record
                done += 1
                if progress is not None:
                    progress(done, record)

        await asyncio.gather(*(worker() for _ in range(max(1, concurrency))))
    return [r for r in records if r is not None]


def run_searches(
    controller_url: str,
    jobs: Sequence[tuple[BenchTarget, StrategyName]],
    *,
    concurrency: int = 1,
    max_iterations: int = 60,
    progress: Callable[[int, SearchRecord], None] | None = None,
    timeout_s: float = 600.0,
    arm: str = "general",
    api_key: str | None = None,
) -> list[SearchRecord]:
    """Run every (target, strategy) search with ``concurrency`` in flight; records in job order,
    labelled with the detector ``arm`` they ran with; ``api_key`` goes to the controller.

    A search the controller refused or lost is recorded with status ``error``, never raised.
    """
    return asyncio.run(
        _run(controller_url, jobs, concurrency, max_iterations, progress, timeout_s, arm, api_key)
    )


@contextmanager
def local_stack(
    workdir: Path,
    *,
    renderers: int = 1,
    detectors: int = 1,
    render_spp: int | None = None,
    render_width: int | None = None,
    max_concurrent_searches: int | None = None,
    scene_dirs: Sequence[Path] = (),
) -> Iterator[Stack]:
    """The four services as local processes on free loopback ports, a fresh SQLite database in
    ``workdir``. ``render_spp`` and ``render_width`` set the controller's samples per pixel and
    film width for search views (``COSMOS_CONTROLLER_VIEW_SPP``, ``COSMOS_CONTROLLER_VIEW_WIDTH``;
    targets always ask for :data:`TARGET_SPP` at the scene's film explicitly); ``scene_dirs``
    come before any ``COSMOS_SCENES_DIR`` of this process."""
    env: dict[str, str] = {}
    if scene_dirs:
        inherited = [os.environ["COSMOS_SCENES_DIR"]] if os.environ.get("COSMOS_SCENES_DIR") else []
        env["COSMOS_SCENES_DIR"] = os.pathsep.join([*(str(d) for d in scene_dirs), *inherited])
    if render_spp is not None:
        env["COSMOS_CONTROLLER_VIEW_SPP"] = str(render_spp)
    if render_width is not None:
        env["COSMOS_CONTROLLER_VIEW_WIDTH"] = str(render_width)
    if max_concurrent_searches is not None:
        env["COSMOS_CONTROLLER_MAX_CONCURRENT_SEARCHES"] = str(max_concurrent_searches)
    with services_stack(workdir, renderers=renderers, detectors=detectors, env=env) as stack:
        yield stack
