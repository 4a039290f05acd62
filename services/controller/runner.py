"""The controller's queue of searches and its workers: queueing, cancelling, deleting, retrying.

Searches run concurrently on ``max_concurrent`` workers, each through the search loop
(:mod:`~services.controller.loop`, or :mod:`~services.controller.free_loop` for a free
search); the rest wait in a FIFO queue. A search whose stage stayed
away longer than the outage budget (:mod:`~services.controller.outages`) can be queued again
with :meth:`SearchRunner.retry`.

A cancel (:meth:`SearchRunner.cancel`) is never lost, whenever it arrives: it is recorded at
once, and the store keeps a cancelled search cancelled whatever its stopping run writes after it
(a run cancelled before its first write used to set it 'running' again, for a restart to resume).

On PostgreSQL, controllers share the searches (:mod:`~services.controller.store.leases`): a
runner runs a search only under its lease, renews its leases and claims the searches whose lease
ran out (a controller died or was cut off) every third of the lease time, and stops a run whose
lease it lost (taken over, cancelled or deleted through another controller) without writing
again. A run whose database goes away ends; the search stays as recorded, for the next holder.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from datetime import datetime

from pydantic import ValidationError

from services.common.contracts.search import TERMINAL_STATUSES, Search
from services.common.errors import ProblemDetails, problem_type
from services.controller.broker import BrokerError
from services.controller.events import Notifier
from services.controller.failures import SearchFailed
from services.controller.free_loop import FreeSearchLoop
from services.controller.loop import SearchLoop
from services.controller.outages import OutagePolicy, why_not_retryable
from services.controller.stages import Stages
from services.controller.store import (
    FIRST_GENERATION,
    DatabaseUnavailable,
    Lease,
    LeaseLost,
    Leases,
    SearchStore,
)

__all__ = ["NotRetryable", "SearchRunner", "StillStopping"]

_log = logging.getLogger("cosmos.controller")


class StillStopping(Exception):
    """A cancelled search whose run has not stopped yet (its last writes are to come): it cannot
    be deleted yet."""


class NotRetryable(Exception):
    """A search that :meth:`SearchRunner.retry` does not queue again; the message says why."""


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
        leases: Leases | None = None,
    ) -> None:
        self.store = store
        self.stages = stages
        self.notifier = notifier
        self.max_concurrent = max_concurrent
        self.outage_budget_s = outage_budget_s
        outages = OutagePolicy(stages, outage_budget_s)
        self.loop = SearchLoop(store, stages, notifier, outages)
        self.free_loop = FreeSearchLoop(store, stages, notifier, outages)
        self._queue: asyncio.Queue[str] = asyncio.Queue()
        self._workers: list[asyncio.Task[None]] = []
        self._running: dict[str, asyncio.Task[None]] = {}
        self._cancelled: set[str] = set()
        self._submitted: dict[str, tuple[Search, bytes]] = {}  # new searches, not yet picked up
        self.leases = leases
        self._held: dict[str, Lease] = {}  # the leases of the searches queued or run here
        self._lost: set[str] = set()  # searches whose lease went elsewhere: stop, write nothing
        self._heartbeat: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Start the workers and queue every search a previous run left unfinished."""
        for _ in range(self.max_concurrent):
            self._workers.append(asyncio.create_task(self._work()))
        if self.leases is not None:  # the unfinished searches are claimed, by whoever is free
            self._heartbeat = asyncio.create_task(self._keep_leases(self.leases))
            return
        for search_id in self.store.unfinished():
            _log.info("resuming search %s", search_id)
            self.submit(search_id)

    async def _keep_leases(self, leases: Leases) -> None:
        """Renew the leases held, stop the runs of those lost, claim what no one holds."""
        while True:
            try:
                await self.beat(leases)
            except DatabaseUnavailable as exc:
                _log.warning("leases not renewed: %s", exc)
            await asyncio.sleep(leases.lease_s / 3)

    async def beat(self, leases: Leases) -> None:
        """One heartbeat (:meth:`_keep_leases`)."""
        held = list(self._held.values())
        kept = set(await asyncio.to_thread(leases.renew, held))
        for lease in held:
            if lease not in kept and self._held.get(lease.search_id) == lease:
                _log.info("search %s is no longer this controller's", lease.search_id)
                self._lost.add(lease.search_id)
                task = self._running.get(lease.search_id)
                if task is not None:
                    task.cancel()
        free = self.max_concurrent - len(self._running) - self._queue.qsize()
        for lease in await asyncio.to_thread(leases.claim, free):
            _log.info("taking over search %s (lease %d)", lease.search_id, lease.generation)
            self._held[lease.search_id] = lease
            self._lost.discard(lease.search_id)
            self._queue.put_nowait(lease.search_id)

    async def close(self) -> None:
        """Stop the workers; running searches stay 'running' and resume on the next start (or,
        on PostgreSQL, at once on another controller: their leases are released)."""
        if self._heartbeat is not None:
            self._heartbeat.cancel()
            await asyncio.wait([self._heartbeat])
        for worker in self._workers:
            worker.cancel()
        if self._workers:
            # wait() leaves the workers' cancellations to them and lets close()'s own through
            await asyncio.wait(self._workers)
        workers, self._workers = self._workers, []
        for worker in workers:
            if not worker.cancelled():
                worker.result()  # a worker that failed: its error, not silence

    def submit(
        self,
        search_id: str,
        *,
        recorded: tuple[Search, bytes] | None = None,
        leased: bool = False,
    ) -> None:
        """Queue a search; a new one hands in its record and target image, already stored, so
        that it starts without reading them back, and ``leased`` when this controller's
        :attr:`leases` took its first lease as it was recorded (:meth:`Leases.hold`)."""
        if recorded is not None:
            self._submitted[search_id] = recorded
        if leased and self.leases is not None:
            self._held[search_id] = Lease(search_id, FIRST_GENERATION)
        self._queue.put_nowait(search_id)

    @property
    def queued(self) -> int:
        return self._queue.qsize()

    @property
    def running(self) -> int:
        return len(self._running)

    @property
    def stopping(self) -> int:
        """Cancelled searches whose runs have yet to stop (a finished run forgets its cancel)."""
        return len(self._cancelled)

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
            self.notifier.publish(search_id)  # its followers end
        return deleted

    def why_not_retryable(self, search: Search) -> str | None:
        """Why :meth:`retry` would refuse ``search``, or None if it would take it."""
        why = why_not_retryable(search)
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
        if search is None:  # retried through another controller since it was read
            raise NotRetryable(f"search {search_id} is no longer failed; it was retried already")
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
            if search_id in self._running:  # queued twice (submitted here, and claimed)
                continue
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

    async def _lease(self, search_id: str) -> Lease | None:
        """The lease to run ``search_id`` under (taken now for a search submitted here), or
        None when another controller holds it; always None on SQLite."""
        if self.leases is None:
            return None
        # The database is called on threads: one that hangs holds this search only, never the
        # event loop (and with it the probes and every other search).
        lease = self._held.get(search_id) or await asyncio.to_thread(self.leases.take, search_id)
        if lease is not None:
            self._held[search_id] = lease
        return lease

    async def _run(self, search_id: str) -> None:
        try:
            lease = await self._lease(search_id)
        except DatabaseUnavailable as exc:
            _log.warning("search %s not started: %s", search_id, exc)
            return
        if self.leases is not None and lease is None:
            self._submitted.pop(search_id, None)
            self.stages.forget_early(search_id)
            return  # another controller runs it
        try:
            await self._run_held(search_id, lease)
        finally:
            if lease is not None:
                self._held.pop(search_id, None)
                self._lost.discard(search_id)
                await asyncio.to_thread(self._release, lease)

    def _release(self, lease: Lease) -> None:
        if self.leases is None:
            return
        try:
            self.leases.release(lease)
        except DatabaseUnavailable as exc:  # it runs out by itself
            _log.warning("lease of search %s not released: %s", lease.search_id, exc)

    async def _run_held(self, search_id: str, lease: Lease | None) -> None:
        submitted = self._submitted.pop(search_id, None)
        search: Search | None
        image: bytes | None
        if submitted is None:
            search, image = await asyncio.to_thread(self.store.get, search_id), None
        else:
            search, image = submitted
        if search is None or search.status in TERMINAL_STATUSES or search_id in self._cancelled:
            self.stages.forget_early(search_id)
            self._cancelled.discard(search_id)  # its run, the only one to come, is over
            return
        try:
            loop = self.free_loop if search.mode == "free" else self.loop
            if image is None:
                image = await asyncio.to_thread(self.store.image, search_id)
            await loop.run(search, image, lease)
        except asyncio.CancelledError:
            if search_id in self._cancelled or search_id in self._lost:
                return
            raise
        except LeaseLost as lost:
            _log.info("search %s stopped here: %s", search_id, lost)
        except DatabaseUnavailable as exc:  # recorded so far stays; the next holder resumes
            _log.warning("search %s stopped: %s", search_id, exc)
        except SearchFailed as failed:
            # what the error leaves out: the broker's reasons (replica addresses), the answer
            cause = failed.__cause__
            why = f" ({cause})" if isinstance(cause, BrokerError | ValidationError) else ""
            _log.warning("search %s failed: %s%s", search_id, failed.problem.detail, why)
            self._record_failure(search_id, lease, failed.problem)
        except Exception:  # a bug must fail the search, not the worker
            _log.exception("search %s crashed", search_id)
            self._record_failure(
                search_id,
                lease,
                ProblemDetails(
                    type=problem_type("internal-error"),
                    title="Internal error",
                    status=500,
                    detail="the search failed unexpectedly; the error was logged",
                ),
            )
        finally:
            self.stages.forget_early(search_id)  # a start view the search did not take
            self._cancelled.discard(search_id)  # a cancelled search is never run again
            self.notifier.publish(search_id)

    def _record_failure(self, search_id: str, lease: Lease | None, problem: ProblemDetails) -> None:
        try:
            self.store.update(search_id, lease, status="failed", error=problem)
        except (LeaseLost, DatabaseUnavailable) as exc:
            _log.warning("failure of search %s not recorded: %s", search_id, exc)
