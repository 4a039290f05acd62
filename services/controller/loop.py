"""The search loop, as the paper's: render the view at the current pose, detect its objects, ask
the optimizer for the next pose, and move there or stop.

A search detects its target once, then per iteration renders the current grid pose, detects the
objects in it and asks the optimizer for the next pose, until the optimizer says done or
``max_iterations`` views were rendered.

A search that runs out of iterations, or whose strategy goes round in circles, still succeeds,
with an *unconfirmed* answer (``result.confirmed`` false): the visited pose whose view matched
the target best by the optimizer's match score. An unconfirmed answer of the reprojection
strategy (or one confirmed near a boundary between grid poses, or looking steeply down) is
settled by one render more, with its depth, at its pose: the dense fit from it may move the
answer to the grid pose nearest the camera it finds, unconfirmed (:mod:`.grid_edges`). Only real
errors fail a search (a stage unavailable for longer than the outage budget
(:mod:`~services.controller.outages`) or refusing, nothing detected in the target, a grid the
optimizer cannot search).

The optimizer's question is made from what the search has seen
(:mod:`~services.controller.progress`, with the scene's object classes when they apply).

The target's detection overlaps the start view's render, which a search submitted to an idle
runner had started before its submission was even stored (:meth:`Stages.render_early`: its first
render time is then the part the search waited for). A search submitted without a start detects
its target first and starts where the target's detections predict (:mod:`.start`). A pose
already rendered in this search is never rendered again: its detections are reused.
Every view is rendered with the settings the search recorded when it was submitted
(``Search.view_settings``: samples per pixel, film width), so a search resumed by a controller
started with other settings goes on seeing what it saw; a search stored by an earlier version,
which recorded none, takes the controller's current ones.

Every iteration is recorded as soon as the next view's render is on its way (the write overlaps
the render, :mod:`~services.controller.writes`), and before the search ends, fails or is
cancelled; a search interrupted by a restart resumes from its last recorded iteration (the
optimizer is stateless: it is given the whole history every time).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from pydantic import ValidationError

from services.common.contracts.detect import DetectResponse
from services.common.contracts.optimize import (
    GridPose,
    NextPoseResponse,
    TargetImage,
    UnsupportedGridError,
    searchable_grid,
)
from services.common.contracts.search import Iteration, Search, SearchResult, StageTimings
from services.common.geometry.pose import Pose
from services.common.images import media_type_of
from services.controller.events import Notifier
from services.controller.failures import SearchFailed, failure, unreadable_answer
from services.controller.grid_edges import (
    EDGE_STRATEGY,
    near_a_boundary,
    settle_by_edges,
    steep,
)
from services.controller.outages import OutagePolicy
from services.controller.progress import Progress, View, at
from services.controller.stages import Stages
from services.controller.start import StartPicker, predicts_start
from services.controller.store import Lease, SearchStore
from services.controller.writes import Writes

__all__ = ["SearchLoop"]


def _retrieve(task: asyncio.Task[Any]) -> None:
    """Mark a finished task's exception as retrieved. Its awaiter may have stopped before
    awaiting it (another stage call failed first), and asyncio would log "Task exception was
    never retrieved" for an error the search already answers with its own."""
    if not task.cancelled():
        task.exception()


def _result_of(last: Iteration, renders: int) -> SearchResult:
    """The search's result from its final iteration: confirmed unless the optimizer found it
    ambiguous (a confirmed answer is one the search vouches for)."""
    found = last.estimate_grid or last.pose
    refined = last.estimate or Pose(theta_deg=found.theta_deg, phi_deg=found.phi_deg)
    reason = last.reason
    if last.ambiguous:
        reason = f"not confirmed: the answer is ambiguous; {reason}"
    return SearchResult(
        pose=found,
        refined_pose=refined,
        confidence=last.confidence,
        renders=renders,
        ambiguous=last.ambiguous,
        confirmed=not last.ambiguous,
        reason=reason,
    )


def _best_visited(history: list[Iteration], renders: int, why: str) -> SearchResult:
    """The any-time answer: the visited pose whose view matched the target best (by the
    optimizer's match score; the earliest among equals), unconfirmed, saying ``why``."""
    best = max(history, key=lambda it: (it.match.score if it.match is not None else 0.0, -it.index))
    score = best.match.score if best.match is not None else 0.0
    # The estimate refines this pose only when it is nearest to it.
    refined = best.estimate if best.estimate_grid == best.pose and best.estimate else None
    rms = best.match.rms_px if best.match is not None else None
    how = (
        f"RMS {rms:.2f} px over {best.match.pairs} pairs"
        if best.match is not None and rms is not None
        else "no detection pairs with the target"
    )
    return SearchResult(
        pose=best.pose,
        refined_pose=refined or Pose(theta_deg=best.pose.theta_deg, phi_deg=best.pose.phi_deg),
        confidence=score,
        renders=renders,
        ambiguous=best.ambiguous,
        confirmed=False,
        reason=(
            f"not confirmed: {why}; the best match was view {best.index} at lat "
            f"{best.pose.index.lat} lon {best.pose.index.lon} (score {score:.2f}, {how})"
        ),
    )


def _timings(render_ms: float, detect_ms: float, optimize_ms: float, t0: float) -> StageTimings:
    """An iteration's stage times, and its total since ``t0`` (:func:`time.perf_counter`)."""
    total_ms = (time.perf_counter() - t0) * 1000
    return StageTimings(
        render_ms=render_ms, detect_ms=detect_ms, optimize_ms=optimize_ms, total_ms=total_ms
    )


class SearchLoop:
    """Runs one search at a time to its end, over the stages (through the outage policy),
    recording it in the store and waking its followers."""

    def __init__(
        self, store: SearchStore, stages: Stages, notifier: Notifier, outages: OutagePolicy
    ) -> None:
        self.store = store
        self.stages = stages
        self.notifier = notifier
        self.outages = outages
        self.start = StartPicker(stages, outages)

    async def _detect(self, image: bytes, media_type: str, sid: str, scene: str) -> DetectResponse:
        return await self.outages.call(
            sid, lambda: self.stages.detect(image, media_type, sid, scene=scene)
        )

    async def _observe(
        self, search: Search, pose: GridPose, target_image: bytes | None
    ) -> tuple[DetectResponse, DetectResponse | None, float, float]:
        """Render and detect ``pose``; detect ``target_image`` too (while rendering), if given.

        Returns the view's detections, the target's (or None), render and detect milliseconds.
        """
        sid = search.id
        target_task = None
        if target_image is not None:
            target_task = asyncio.create_task(
                self._detect(target_image, media_type_of(target_image), sid, search.scene)
            )
            target_task.add_done_callback(_retrieve)
        try:
            t0 = time.perf_counter()
            view_image = await self.outages.call(
                sid,
                lambda: self.stages.render(search.scene, pose.index, sid, search.view_settings),
            )
            t1 = time.perf_counter()
            found = await self._detect(view_image, media_type_of(view_image), sid, search.scene)
            t2 = time.perf_counter()
            seen = await target_task if target_task is not None else None
        finally:
            if target_task is not None and not target_task.done():
                target_task.cancel()
                with contextlib.suppress(asyncio.CancelledError, SearchFailed):
                    await target_task
        return found, seen, (t1 - t0) * 1000, (t2 - t1) * 1000

    async def _observe_while(
        self, writes: Writes, search: Search, pose: GridPose, target_image: bytes | None
    ) -> tuple[DetectResponse, DetectResponse | None, float, float]:
        """:meth:`_observe`, with the search's waiting writes done once its requests are out."""
        observing = asyncio.create_task(self._observe(search, pose, target_image))
        observing.add_done_callback(_retrieve)  # when a write fails before it is awaited
        try:
            # The render request goes out first. It takes the loop a few turns: the task's first
            # step, then (before Python 3.12) aiohttp writes the body from a task of its own.
            for _ in range(3):
                await asyncio.sleep(0)
            await writes.flush()
            return await observing
        finally:
            if not observing.done():
                observing.cancel()
                with contextlib.suppress(asyncio.CancelledError, SearchFailed):
                    await observing

    async def run(self, search: Search, image: bytes, lease: Lease | None = None) -> SearchResult:
        """Run a search to its result, recording every iteration (under ``lease``, when several
        controllers share the database); raises :class:`SearchFailed`, and
        :class:`~services.controller.store.LeaseLost` once another controller holds it."""
        writes = Writes(self.store, self.notifier, search, lease)
        try:
            return await self._iterate(search, image, writes)
        finally:
            await writes.flush()  # what is done is recorded before a failure or a cancellation

    async def _iterate(self, search: Search, image: bytes, writes: Writes) -> SearchResult:
        """The search loop. From the start pose (or where a resumed search stopped):

        1. render the view at the current pose (the target image's objects are detected too,
           the first time);
        2. detect the view's objects (a pose seen before is neither rendered nor detected again);
        3. ask the optimizer for the next pose, given the target and every view so far;
        4. stop when the optimizer says done (the answer is confirmed unless ambiguous) or that
           the search goes round in circles, or after ``max_iterations`` views (both answer the
           best visited pose, unconfirmed); else move to the next pose and go on at 1;
        5. an unconfirmed answer, or one confirmed near a boundary or looking steeply down, is
           settled by the render's edges (:meth:`_settle`).

        Every iteration is recorded (:class:`Writes`); raises :class:`SearchFailed`.
        """
        progress = await self._begin(search, image)
        if progress.finished:  # by an older controller, which recorded no result
            return await writes.succeed(_result_of(progress.history[-1], progress.renders))
        pose = progress.pose
        if predicts_start(progress):  # no start given: the target says where to look first
            pose = await self.start.first_pose(progress, image)
            # nothing detected in the target fails before any render
            await self._target(progress, writes)
        while pose is not None and len(progress.history) < search.max_iterations:
            started = time.perf_counter()
            view, render_ms, detect_ms = await self._look(progress, pose, image, writes)
            target = await self._target(progress, writes)
            answer, optimize_ms = await self._ask_optimizer(progress, target, pose, view)
            timings = _timings(render_ms, detect_ms, optimize_ms, started)
            iteration = progress.add(pose, view, answer, timings)
            new_target = progress.take_unrecorded_target()
            if answer.done:
                result = await self._settle(
                    progress, image, _result_of(iteration, progress.renders)
                )
                return await writes.succeed(result, iteration, new_target)
            if answer.stuck:
                why = (
                    f"the {search.strategy} strategy kept coming back to the same poses "
                    f"after {len(progress.history)} views"
                )
                result = _best_visited(progress.history, progress.renders, why)
                result = await self._settle(progress, image, result)
                return await writes.succeed(result, iteration, new_target)
            writes.hold(iteration, new_target)
            pose = answer.next
        why = f"no view matched the target within {search.max_iterations} views"
        result = _best_visited(progress.history, progress.renders, why)
        return await writes.succeed(await self._settle(progress, image, result))

    async def _settle(self, progress: Progress, image: bytes, result: SearchResult) -> SearchResult:
        """``result``, when the reprojection strategy's and unconfirmed, or confirmed near a
        boundary between grid poses or looking steeply down, settled by a render of its pose
        with depth and the dense fit from it (:mod:`.grid_edges`)."""
        search = progress.search
        if search.strategy != EDGE_STRATEGY or progress.target is None:
            return result
        looks_down = steep(result)
        if result.confirmed and not (looks_down or near_a_boundary(result, progress.grid)):
            return result
        return await settle_by_edges(
            self.stages,
            self.outages,
            search,
            progress.scene,
            progress.grid,
            image,
            progress.target_size,
            result,
            vouch=looks_down,
        )

    async def _begin(self, search: Search, image: bytes) -> Progress:
        """The search's scene and grid, and what it recorded before (nothing when new). A search
        resumed before its target's detections were recorded detects the target ``image`` again.
        """
        scene = await self.outages.call(
            search.id, lambda: self.stages.scene(search.scene, search.id)
        )
        try:
            grid = searchable_grid(scene.spec.search)
        except UnsupportedGridError as exc:  # the scene file changed since the search was taken
            raise failure(
                "unsupported-grid",
                "Grid not supported",
                f"scene {search.scene}'s grid cannot be searched: {exc}",
                status=422,
            ) from exc
        progress = Progress.recorded(search, scene, grid)
        if progress.history and not progress.finished and progress.target is None:
            sid = search.id
            progress.saw_target(await self._detect(image, media_type_of(image), sid, search.scene))
        return progress

    async def _look(
        self, progress: Progress, pose: GridPose, image: bytes, writes: Writes
    ) -> tuple[View, float, float]:
        """The view at ``pose``: rendered and detected, with the target ``image`` while its
        detections are unknown, or the one seen there before. The waiting writes go out
        meanwhile. Returns the view, render and detect milliseconds (0 for a view seen before)."""
        seen_before = progress.views.get(at(pose))
        if seen_before is not None:
            await writes.flush()
            return seen_before, 0.0, 0.0
        target_image = image if progress.target is None else None
        view, seen, render_ms, detect_ms = await self._observe_while(
            writes, progress.search, pose, target_image
        )
        if seen is not None:
            progress.saw_target(seen)
        return view, render_ms, detect_ms

    async def _target(self, progress: Progress, writes: Writes) -> TargetImage:
        """What the optimizer looks for; fails the search (recording the empty detections) when
        the detector found nothing in the target image."""
        if not progress.target:
            await writes.update(target_detections=progress.target)
            raise failure(
                "no-target-objects",
                "Nothing to search for",
                "the detector found no objects in the target image",
                status=422,
            )
        return TargetImage(image_size=progress.target_size, detections=progress.target)

    async def _ask_optimizer(
        self, progress: Progress, target: TargetImage, pose: GridPose, view: View
    ) -> tuple[NextPoseResponse, float]:
        """The optimizer's answer once it sees ``view`` at ``pose``, and its milliseconds."""
        request = progress.request(target, pose, view)
        t0 = time.perf_counter()
        try:
            sid = progress.search.id
            answer = await self.outages.call(sid, lambda: self.stages.optimize(request, sid))
        except ValidationError as exc:
            raise unreadable_answer(exc) from exc
        return answer, (time.perf_counter() - t0) * 1000
