"""The COSMOS Controller's search loop and its queue.

A search detects its target once, then per iteration renders the current grid pose, detects the
objects in it and asks the optimizer for the next pose, until the optimizer says done or
``max_iterations`` views were rendered.

A search that runs out of iterations, or whose strategy goes round in circles, still succeeds,
with an *unconfirmed* answer (``result.confirmed`` false): the visited pose whose view matched
the target best by the optimizer's match score. Only real errors fail a search (a stage
unavailable for longer than ``outage_budget_s`` or refusing, nothing detected in the target, a
grid the optimizer cannot search).

Outages: a stage call that no replica serves waits for a replica to answer again (the broker
probes the stage meanwhile) and is made again, for up to ``outage_budget_s`` after it first
failed; the search's time goes into the waiting call's stage time. A search that waited longer
fails with :data:`OUTAGE` and can be queued again with :meth:`SearchRunner.retry`: it resumes from
its recorded iterations like a search after a restart.

Detector classes: when the target was detected by the scene's own model (``model.scene`` is
the search's scene), its labels are the scene's object classes and the optimizer is told so
(``object_classes``). That holds only while every view of the request came from the very model
(sha256) that detected the target; if a view's model differs (a model swapped mid-search) or
is unknown (a view recorded by an earlier version), the request leaves ``object_classes`` out and
the optimizer treats labels as mere evidence (different labels pair at a cost) rather than
re-detecting the target.

The target's detection overlaps the start view's render, which a search submitted to an idle
runner had started before its submission was even stored (:meth:`Stages.render_early`: its first
render time is then the part the search waited for). A pose already rendered in this search is
never rendered again: its detections are reused.
Every view is rendered with the settings the search recorded when it was submitted
(``Search.view_settings``: samples per pixel, film width), so a search resumed by a controller
started with other settings goes on seeing what it saw; a search stored by an earlier version,
which recorded none, takes the controller's current ones.

Every iteration is recorded as soon as the next view's render is on its way (the write overlaps
the render), and before the search ends, fails or is cancelled; a search interrupted by a restart
resumes from its last recorded iteration (the optimizer is stateless: it is given the whole
history every time).
Searches run concurrently on ``max_concurrent`` workers; the rest wait in a FIFO queue.

A cancel (:meth:`SearchRunner.cancel`) is never lost, whenever it arrives: it is recorded at
once, and the store keeps a cancelled search cancelled whatever its stopping run writes after it
(a run cancelled before its first write used to set it 'running' again, for a restart to resume).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar, Unpack

from pydantic import ValidationError

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.optimize import (
    GridPose,
    NextPoseRequest,
    NextPoseResponse,
    SearchableGrid,
    TargetImage,
    UnsupportedGridError,
    VisitedView,
    searchable_grid,
)
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import (
    OUTAGE,
    TERMINAL_STATUSES,
    Iteration,
    Search,
    SearchResult,
    StageTimings,
)
from services.common.errors import ProblemDetails, problem_type
from services.common.geometry.pose import Pose, PoseQuery
from services.common.images import media_type_of
from services.common.scene_models import ObjectClass, object_classes
from services.controller.broker import BrokerError
from services.controller.events import Notifier
from services.controller.stages import StageError, Stages
from services.controller.store import SearchChanges, SearchStore

__all__ = ["NotRetryable", "SearchRunner", "StillStopping"]

_log = logging.getLogger("cosmos.controller")
T = TypeVar("T")


class StillStopping(Exception):
    """A cancelled search whose run has not stopped yet (its last writes are to come): it cannot
    be deleted yet."""


class NotRetryable(Exception):
    """A search that :meth:`SearchRunner.retry` does not queue again; the message says why."""


class SearchFailed(Exception):
    """A search cannot go on; ``problem`` says why."""

    def __init__(self, problem: ProblemDetails) -> None:
        super().__init__(problem.detail)
        self.problem = problem


def _failure(slug: str, title: str, detail: str, status: int = 502) -> SearchFailed:
    return SearchFailed(
        ProblemDetails(type=problem_type(slug), title=title, status=status, detail=detail)
    )


@dataclass(frozen=True)
class _View:
    """A rendered pose's detections, reused if the search comes back to it, and the sha256 of
    the model that detected them (None when recorded by an earlier version)."""

    image_size: tuple[int, int]
    detections: tuple[Detection, ...]
    model: str | None = None


def _refused(exc: StageError) -> SearchFailed:
    """The search's failure when a stage refused its task (a 4xx answer)."""
    problem = exc.problem
    detail = f"the {exc.stage} refused a task: {problem.detail or problem.title}"
    return _failure("stage-refused", f"{exc.stage.capitalize()} refused", detail, 422)


def _outage(exc: BrokerError, search_id: str, budget_s: float) -> SearchFailed:
    """The search's failure when no replica of a stage served its task and none came back within
    ``budget_s``: what happened and what to do, in words for whoever submitted it.

    The broker's reasons name replica addresses: they go to the log (:meth:`SearchRunner._run`),
    not into the search's error, which every client reads.
    """
    stage = exc.stage
    if exc.reasons:
        what = (
            f"the {stage} was unavailable (no replica could {exc.kind}: each timed out, refused "
            f"the connection or answered with a server error) and did not come back within "
            f"{budget_s:g} s"
        )
    else:
        what = (
            f"no {stage} replica is known (none configured or discovered) and none appeared "
            f"within {budget_s:g} s"
        )
    detail = (
        f"{what}; once GET /health no longer lists the {stage} as unavailable, resume the search "
        f"with POST /searches/{search_id}/retry"
    )
    return SearchFailed(
        ProblemDetails(type=OUTAGE, title=f"No {stage} available", status=503, detail=detail)
    )


def _why_not_retryable(search: Search) -> str | None:
    """Why ``search``'s record says it cannot be retried, or None."""
    if search.status != "failed":
        return (
            f"search {search.id} is {search.status}: only a search that failed because a stage "
            "was unavailable can be retried"
        )
    if search.error is None or search.error.type != OUTAGE:
        why = search.error.title if search.error is not None else "no error recorded"
        return (
            f"search {search.id} failed for a reason a retry does not change ({why}); only a "
            "search that failed because a stage was unavailable can be retried"
        )
    return None


def _retrieve(task: asyncio.Task[Any]) -> None:
    """Mark a finished task's exception as retrieved. Its awaiter may have stopped before
    awaiting it (another stage call failed first), and asyncio would log "Task exception was
    never retrieved" for an error the search already answers with its own."""
    if not task.cancelled():
        task.exception()


def _unreadable_answer(exc: ValidationError) -> SearchFailed:
    """The search's failure when the optimizer's answer does not fit the contract: the fields
    at fault, without pydantic's dump of the answer."""
    errors = [
        {"field": ".".join(str(part) for part in err["loc"]), "message": err["msg"]}
        for err in exc.errors(include_url=False, include_context=False, include_input=False)
    ]
    named = "; ".join(f"{err['field']}: {err['message']}" for err in errors[:3])
    more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
    detail = (
        f"the optimizer's answer does not fit this controller's contract ({named}{more}); "
        "the optimizer and the controller are probably of different versions"
    )
    problem = ProblemDetails(
        type=problem_type("bad-optimizer-answer"),
        title="Bad optimizer answer",
        status=502,
        detail=detail,
        errors=errors,
    )
    return SearchFailed(problem)


def _result_of(last: Iteration, renders: int) -> SearchResult:
    """The search's result from its final iteration."""
    found = last.estimate_grid or last.pose
    refined = last.estimate or Pose(theta_deg=found.theta_deg, phi_deg=found.phi_deg)
    return SearchResult(
        pose=found,
        refined_pose=refined,
        confidence=last.confidence,
        renders=renders,
        ambiguous=last.ambiguous,
        reason=last.reason,
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


def _target_changes(
    target: DetectResponse | None, **changes: Unpack[SearchChanges]
) -> SearchChanges:
    """``changes``, and the target's detections and model when ``target`` is given."""
    if target is not None:
        changes["target_detections"] = target.detections
        changes["target_model"] = target.model
    return changes


def _classes_for(
    search: Search,
    scene: SceneDetail,
    target_model: ModelInfo | None,
    views: Iterable[_View],
) -> tuple[ObjectClass, ...] | None:
    """The scene's object classes when the target and every view came from the scene's own
    model (module docstring), else None."""
    if target_model is None or target_model.scene != search.scene:
        return None
    if any(view.model != target_model.sha256 for view in views):
        return None
    return object_classes(scene.spec)


def _timings(render_ms: float, detect_ms: float, optimize_ms: float, t0: float) -> StageTimings:
    """An iteration's stage times, and its total since ``t0`` (:func:`time.perf_counter`)."""
    total_ms = (time.perf_counter() - t0) * 1000
    return StageTimings(
        render_ms=render_ms, detect_ms=detect_ms, optimize_ms=optimize_ms, total_ms=total_ms
    )


def _at(pose: GridPose) -> tuple[int, int]:
    return (pose.index.lat, pose.index.lon)


def _visited(
    pose: GridPose, image_size: tuple[int, int], detections: tuple[Detection, ...]
) -> VisitedView:
    return VisitedView(
        pose=PoseQuery(lat=pose.index.lat, lon=pose.index.lon),
        image_size=image_size,
        detections=detections,
    )


@dataclass
class _Progress:
    """What a search looks for and what it has seen: its iterations, the view at every pose it
    rendered (a pose is rendered once: a view is reused when the search comes back to it), and
    the target's detections, with those the store does not hold yet."""

    search: Search
    scene: SceneDetail
    grid: SearchableGrid
    history: list[Iteration]
    views: dict[tuple[int, int], _View]
    target: tuple[Detection, ...] | None
    target_size: tuple[int, int]
    target_model: ModelInfo | None  # None for a target recorded by an earlier version
    unrecorded_target: DetectResponse | None = None  # recorded with the next iteration

    @classmethod
    def recorded(cls, search: Search, scene: SceneDetail, grid: SearchableGrid) -> _Progress:
        """What ``search`` recorded: nothing for a new search, its iterations for a resumed one."""
        history = list(search.iterations)
        views = {
            _at(it.pose): _View(it.image_size, it.detections, it.detector_sha256) for it in history
        }
        return cls(
            search,
            scene,
            grid,
            history,
            views,
            search.target_detections,
            search.target_size,
            search.target_model,
        )

    @property
    def renders(self) -> int:
        return len(self.views)

    @property
    def finished(self) -> bool:
        """Whether the last recorded iteration was done."""
        return bool(self.history) and self.history[-1].done

    @property
    def pose(self) -> GridPose | None:
        """Where the search goes on: the start pose, or the next pose of its last iteration."""
        return self.history[-1].next_pose if self.history else self.search.start

    def saw_target(self, seen: DetectResponse) -> None:
        """Take the target's detections, to be recorded with the next iteration."""
        self.target = seen.detections
        self.target_size = seen.image_size
        self.target_model = seen.model
        self.unrecorded_target = seen

    def take_unrecorded_target(self) -> DetectResponse | None:
        """The target's detections if the store does not hold them yet (then they are its)."""
        seen, self.unrecorded_target = self.unrecorded_target, None
        return seen

    def request(self, target: TargetImage, pose: GridPose, view: _View) -> NextPoseRequest:
        """The optimizer's question once it sees ``view`` at ``pose``: the target and every view
        so far, with the scene's object classes when they apply (:func:`_classes_for`)."""
        history = [_visited(it.pose, it.image_size, it.detections) for it in self.history]
        history.append(_visited(pose, view.image_size, view.detections))
        classes = _classes_for(self.search, self.scene, self.target_model, self.views.values())
        return NextPoseRequest(
            strategy=self.search.strategy,
            camera=self.scene.spec.camera,
            grid=self.grid,
            target=target,
            history=tuple(history),
            **({} if classes is None else {"object_classes": classes}),
        )

    def add(
        self, pose: GridPose, view: _View, answer: NextPoseResponse, timings: StageTimings
    ) -> Iteration:
        """Record, in the history, ``view`` at ``pose`` and the optimizer's ``answer`` to it."""
        estimate = answer.estimate
        iteration = Iteration(
            index=len(self.history),
            pose=pose,
            image_size=view.image_size,
            detections=view.detections,
            detector_sha256=view.model,
            timings=timings,
            estimate=(
                Pose(theta_deg=estimate.theta_deg, phi_deg=estimate.phi_deg)
                if estimate is not None
                else None
            ),
            estimate_grid=estimate.grid if estimate is not None else None,
            confidence=estimate.confidence if estimate is not None else 0.0,
            ambiguous=answer.ambiguous,
            next_pose=answer.next,
            done=answer.done,
            reason=answer.reason,
            match=answer.match,
        )
        self.history.append(iteration)
        return iteration


class _Writes:
    """A search's writes: those that can wait for its next stage requests (the running status
    and the last iteration: done while the next view renders, they cost the search no time),
    and its success."""

    def __init__(self, store: SearchStore, notifier: Notifier, search: Search) -> None:
        self.store = store
        self.notifier = notifier
        self.sid = search.id
        self._running = search.status == "running"
        self._iteration: tuple[Iteration, DetectResponse | None] | None = None

    def hold(self, iteration: Iteration, target: DetectResponse | None) -> None:
        """Record ``iteration`` (with the target's detections and model, when new) at the next
        flush."""
        self._iteration = (iteration, target)

    def flush(self) -> None:
        """Write what waits, and wake the search's followers."""
        if self._running and self._iteration is None:
            return
        if not self._running:
            self.store.update(self.sid, status="running")
            self._running = True
        if self._iteration is not None:
            iteration, target = self._iteration
            self.store.add_iteration(self.sid, iteration, **_target_changes(target))
            self._iteration = None
        self.notifier.publish(self.sid)

    def succeed(
        self,
        result: SearchResult,
        final: Iteration | None = None,
        target: DetectResponse | None = None,
    ) -> SearchResult:
        """Write what waits, then the search's success with ``result``: with its ``final``
        iteration (and the target's detections, when new) if that is not recorded yet. The
        search's followers are woken when its run ends."""
        self.flush()
        if final is None:
            self.store.update(self.sid, status="succeeded", result=result)
        else:
            changes = _target_changes(target, status="succeeded", result=result)
            self.store.add_iteration(self.sid, final, **changes)
        return result


class SearchRunner:
    """Runs queued searches on a bounded number of workers."""

    def __init__(
        self,
        store: SearchStore,
        stages: Stages,
        notifier: Notifier,
        max_concurrent: int,
        *,
        outage_budget_s: float = 60.0,
    ) -> None:
        self.store = store
        self.stages = stages
        self.notifier = notifier
        self.max_concurrent = max_concurrent
        self.outage_budget_s = outage_budget_s
        self._queue: asyncio.Queue[str] = asyncio.Queue()
        self._workers: list[asyncio.Task[None]] = []
        self._running: dict[str, asyncio.Task[None]] = {}
        self._cancelled: set[str] = set()
        self._submitted: dict[str, tuple[Search, bytes]] = {}  # new searches, not yet picked up

    async def start(self) -> None:
        """Start the workers and queue every search a previous run left unfinished."""
        for _ in range(self.max_concurrent):
            self._workers.append(asyncio.create_task(self._work()))
        for search_id in self.store.unfinished():
            _log.info("resuming search %s", search_id)
            self.submit(search_id)

    async def close(self) -> None:
        """Stop the workers; running searches stay 'running' and resume on the next start."""
        for worker in self._workers:
            worker.cancel()
        if self._workers:
            # wait() leaves the workers' cancellations to them and lets close()'s own through
            await asyncio.wait(self._workers)
        workers, self._workers = self._workers, []
        for worker in workers:
            if not worker.cancelled():
                worker.result()  # a worker that failed: its error, not silence

    def submit(self, search_id: str, *, recorded: tuple[Search, bytes] | None = None) -> None:
        """Queue a search; a new one hands in its record and target image, already stored, so
        that it starts without reading them back."""
        if recorded is not None:
            self._submitted[search_id] = recorded
        self._queue.put_nowait(search_id)

    @property
    def queued(self) -> int:
        return self._queue.qsize()

    @property
    def running(self) -> int:
        return len(self._running)

    @property
    def idle(self) -> bool:
        """Whether a search submitted now would start at once (a worker is free, none waits)."""
        return self._queue.empty() and len(self._running) < self.max_concurrent

    def cancel(self, search_id: str) -> Search:
        """Cancel a queued or running search (a finished one is left as it is)."""
        search = self.store.get(search_id)
        if search is None:
            raise KeyError(search_id)
        if search.status in TERMINAL_STATUSES:
            return search
        self._cancelled.add(search_id)
        # A task cancelled before its first step never runs its own clean-up.
        self._submitted.pop(search_id, None)
        self.stages.forget_early(search_id)
        task = self._running.get(search_id)
        if task is not None:
            task.cancel()
        search = self.store.update(search_id, status="cancelled")
        self.notifier.publish(search_id)
        return search

    def delete(self, search_id: str) -> tuple[str | None, datetime] | None:
        """Delete a finished, failed or cancelled search with its image and iterations: its
        owner and creation time, or None when there is no such search (a queued or running one
        is cancelled first, :meth:`cancel`). Raises :class:`StillStopping` while a cancelled
        search's run winds down."""
        if search_id in self._running:
            raise StillStopping(search_id)
        deleted = self.store.delete_finished(search_id)
        if deleted is not None:
            self._cancelled.discard(search_id)
            self.notifier.publish(search_id)  # its followers end
        return deleted

    def why_not_retryable(self, search: Search) -> str | None:
        """Why :meth:`retry` would refuse ``search``, or None if it would take it."""
        why = _why_not_retryable(search)
        if why is None and not self.store.holds_image(search.id):  # failed before it was kept
            why = f"search {search.id} no longer holds its target image; submit it again"
        return why

    def retry(self, search_id: str) -> Search:
        """Queue again a search that failed because a stage was unavailable for longer than it
        waits (:data:`OUTAGE`): it resumes from its recorded iterations, as after a restart.

        Raises ``KeyError`` for an unknown search and :class:`NotRetryable` for any other.
        """
        search = self.store.get(search_id)
        if search is None:
            raise KeyError(search_id)
        why = self.why_not_retryable(search)
        if why is not None:
            raise NotRetryable(why)
        search = self.store.reopen(search_id)
        _log.info("retrying search %s", search_id)
        self.submit(search_id)
        self.notifier.publish(search_id)
        return search

    async def _work(self) -> None:
        worker = asyncio.current_task()
        if worker is None:
            raise RuntimeError("a worker runs as a task")
        while True:
            search_id = await self._queue.get()
            task = asyncio.create_task(self._run(search_id))
            self._running[search_id] = task
            try:
                await asyncio.shield(task)
            except asyncio.CancelledError:
                # The shield raises when the search's task is cancelled (before it ran) and
                # when this worker is (close()), also once the search has just ended: only a
                # cancellation requested of this worker stops it.
                if not worker.cancelling():
                    continue  # the search was cancelled, not this worker
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
                raise
            finally:
                self._running.pop(search_id, None)

    async def _run(self, search_id: str) -> None:
        search, image = self._submitted.pop(search_id, None) or (self.store.get(search_id), None)
        if search is None or search.status in TERMINAL_STATUSES or search_id in self._cancelled:
            self.stages.forget_early(search_id)
            return
        try:
            await self._search(search, image or self.store.image(search_id))
        except asyncio.CancelledError:
            if search_id in self._cancelled:
                return
            raise
        except SearchFailed as failed:
            # what the error leaves out: the broker's reasons (replica addresses), the answer
            cause = failed.__cause__
            why = f" ({cause})" if isinstance(cause, BrokerError | ValidationError) else ""
            _log.warning("search %s failed: %s%s", search_id, failed.problem.detail, why)
            self.store.update(search_id, status="failed", error=failed.problem)
        except Exception:  # a bug must fail the search, not the worker
            _log.exception("search %s crashed", search_id)
            self.store.update(
                search_id,
                status="failed",
                error=ProblemDetails(
                    type=problem_type("internal-error"),
                    title="Internal error",
                    status=500,
                    detail="the search failed unexpectedly; the error was logged",
                ),
            )
        finally:
            self.stages.forget_early(search_id)  # a start view the search did not take
            self.notifier.publish(search_id)

    async def _stage(self, search_id: str, call: Callable[[], Awaitable[T]]) -> T:
        """``call()``, one stage call of a search, riding out an outage of its stage.

        When no replica serves the call (:class:`BrokerError`), the search waits for one to
        answer again (:meth:`Stages.wait_for_replica`: the broker probes the stage meanwhile)
        and calls again, for up to ``outage_budget_s`` after the first failure. A stage that
        refuses the call, or stays away longer, fails the search.
        """
        since: float | None = None
        while True:
            try:
                answer = await call()
            except StageError as exc:
                raise _refused(exc) from exc
            except BrokerError as exc:
                now = time.monotonic()
                if since is None:
                    since = now
                    _log.warning(
                        "search %s waits up to %g s for the %s: %s",
                        search_id,
                        self.outage_budget_s,
                        exc.stage,
                        exc,
                    )
                left = since + self.outage_budget_s - now
                if left <= 0 or not await self.stages.wait_for_replica(exc.stage, left):
                    raise _outage(exc, search_id, self.outage_budget_s) from exc
                continue
            if since is not None:
                _log.info("search %s goes on after %.1f s", search_id, time.monotonic() - since)
            return answer

    async def _detect(self, image: bytes, media_type: str, sid: str, scene: str) -> DetectResponse:
        return await self._stage(
            sid, lambda: self.stages.detect(image, media_type, sid, scene=scene)
        )

    async def _observe(
        self, search: Search, pose: GridPose, target_image: bytes | None
    ) -> tuple[_View, DetectResponse | None, float, float]:
        """Render and detect ``pose``; detect ``target_image`` too (while rendering), if given.

        Returns the view, the target's detections (or None), render and detect milliseconds.
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
            view_image = await self._stage(
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
        view = _View(found.image_size, found.detections, found.model.sha256)
        return view, seen, (t1 - t0) * 1000, (t2 - t1) * 1000

    async def _observe_while(
        self, writes: _Writes, search: Search, pose: GridPose, target_image: bytes | None
    ) -> tuple[_View, DetectResponse | None, float, float]:
        """:meth:`_observe`, with the search's waiting writes done once its requests are out."""
        observing = asyncio.create_task(self._observe(search, pose, target_image))
        observing.add_done_callback(_retrieve)  # when a write fails before it is awaited
        try:
            # The render request goes out first. It takes the loop a few turns: the task's first
            # step, then (before Python 3.12) aiohttp writes the body from a task of its own.
            for _ in range(3):
                await asyncio.sleep(0)
            writes.flush()
            return await observing
        finally:
            if not observing.done():
                observing.cancel()
                with contextlib.suppress(asyncio.CancelledError, SearchFailed):
                    await observing

    async def _search(self, search: Search, image: bytes) -> SearchResult:
        """Run a search to its result, recording every iteration; raises :class:`SearchFailed`."""
        writes = _Writes(self.store, self.notifier, search)
        try:
            return await self._iterate(search, image, writes)
        finally:
            writes.flush()  # what is done is recorded before a failure or a cancellation

    async def _iterate(self, search: Search, image: bytes, writes: _Writes) -> SearchResult:
        """The search loop. From the start pose (or where a resumed search stopped):

        1. render the view at the current pose (the target image's objects are detected too,
           the first time);
        2. detect the view's objects (a pose seen before is neither rendered nor detected again);
        3. ask the optimizer for the next pose, given the target and every view so far;
        4. stop when the optimizer says done (the answer is confirmed) or that the search goes
           round in circles, or after ``max_iterations`` views (both answer the best visited
           pose, unconfirmed); else move to the next pose and go on at 1.

        Every iteration is recorded (:class:`_Writes`); raises :class:`SearchFailed`.
        """
        progress = await self._begin(search, image)
        if progress.finished:  # by an older controller, which recorded no result
            return writes.succeed(_result_of(progress.history[-1], progress.renders))
        pose = progress.pose
        while pose is not None and len(progress.history) < search.max_iterations:
            started = time.perf_counter()
            view, render_ms, detect_ms = await self._look(progress, pose, image, writes)
            target = self._target(progress)
            answer, optimize_ms = await self._ask_optimizer(progress, target, pose, view)
            timings = _timings(render_ms, detect_ms, optimize_ms, started)
            iteration = progress.add(pose, view, answer, timings)
            new_target = progress.take_unrecorded_target()
            if answer.done:
                result = _result_of(iteration, progress.renders)
                return writes.succeed(result, iteration, new_target)
            if answer.stuck:
                why = (
                    f"the {search.strategy} strategy kept coming back to the same poses "
                    f"after {len(progress.history)} views"
                )
                result = _best_visited(progress.history, progress.renders, why)
                return writes.succeed(result, iteration, new_target)
            writes.hold(iteration, new_target)
            pose = answer.next
        why = f"no view matched the target within {search.max_iterations} views"
        return writes.succeed(_best_visited(progress.history, progress.renders, why))

    async def _begin(self, search: Search, image: bytes) -> _Progress:
        """The search's scene and grid, and what it recorded before (nothing when new). A search
        resumed before its target's detections were recorded detects the target ``image`` again.
        """
        scene = await self._stage(search.id, lambda: self.stages.scene(search.scene, search.id))
        try:
            grid = searchable_grid(scene.spec.search)
        except UnsupportedGridError as exc:  # the scene file changed since the search was taken
            raise _failure(
                "unsupported-grid",
                "Grid not supported",
                f"scene {search.scene}'s grid cannot be searched: {exc}",
                status=422,
            ) from exc
        progress = _Progress.recorded(search, scene, grid)
        if progress.history and not progress.finished and progress.target is None:
            sid = search.id
            progress.saw_target(await self._detect(image, media_type_of(image), sid, search.scene))
        return progress

    async def _look(
        self, progress: _Progress, pose: GridPose, image: bytes, writes: _Writes
    ) -> tuple[_View, float, float]:
        """The view at ``pose``: rendered and detected, with the target ``image`` while its
        detections are unknown, or the one seen there before. The waiting writes go out
        meanwhile. Returns the view, render and detect milliseconds (0 for a view seen before)."""
        seen_before = progress.views.get(_at(pose))
        if seen_before is not None:
            writes.flush()
            return seen_before, 0.0, 0.0
        target_image = image if progress.target is None else None
        view, seen, render_ms, detect_ms = await self._observe_while(
            writes, progress.search, pose, target_image
        )
        if seen is not None:
            progress.saw_target(seen)
        progress.views[_at(pose)] = view
        return view, render_ms, detect_ms

    def _target(self, progress: _Progress) -> TargetImage:
        """What the optimizer looks for; fails the search (recording the empty detections) when
        the detector found nothing in the target image."""
        if not progress.target:
            self.store.update(progress.search.id, target_detections=progress.target)
            raise _failure(
                "no-target-objects",
                "Nothing to search for",
                "the detector found no objects in the target image",
                status=422,
            )
        return TargetImage(image_size=progress.target_size, detections=progress.target)

    async def _ask_optimizer(
        self, progress: _Progress, target: TargetImage, pose: GridPose, view: _View
    ) -> tuple[NextPoseResponse, float]:
        """The optimizer's answer once it sees ``view`` at ``pose``, and its milliseconds."""
        request = progress.request(target, pose, view)
        t0 = time.perf_counter()
        try:
            sid = progress.search.id
            answer = await self._stage(sid, lambda: self.stages.optimize(request, sid))
        except ValidationError as exc:
            raise _unreadable_answer(exc) from exc
        return answer, (time.perf_counter() - t0) * 1000
