"""A search's store writes, batched so that they cost the search no time: the running status and
each iteration are written while the next view renders, and the success once the search ends.

They run on a worker thread: a database that hangs (a partition, until the connection is given
up) then holds this search only, never the controller's event loop, its probes and its other
searches."""

from __future__ import annotations

import asyncio
from typing import Unpack

from services.common.contracts.detect import DetectResponse
from services.common.contracts.search import Iteration, Search, SearchResult
from services.controller.events import Notifier
from services.controller.store import Lease, SearchChanges, SearchStore

__all__ = ["Writes"]


def _target_changes(
    target: DetectResponse | None, **changes: Unpack[SearchChanges]
) -> SearchChanges:
    """``changes``, and the target's detections and model when ``target`` is given."""
    if target is not None:
        changes["target_detections"] = target.detections
        changes["target_model"] = target.model
    return changes


class Writes:
    """A search's writes: those that can wait for its next stage requests (the running status
    and the last iteration: done while the next view renders, they cost the search no time),
    and its success."""

    def __init__(
        self, store: SearchStore, notifier: Notifier, search: Search, lease: Lease | None = None
    ) -> None:
        self.store = store
        self.lease = lease
        """What every write carries: refused once another controller took the search over."""
        self.notifier = notifier
        self.sid = search.id
        self._running = search.status == "running"
        self._iteration: tuple[Iteration, DetectResponse | None] | None = None

    def hold(self, iteration: Iteration, target: DetectResponse | None) -> None:
        """Record ``iteration`` (with the target's detections and model, when new) at the next
        flush."""
        self._iteration = (iteration, target)

    async def flush(self) -> None:
        """Write what waits, and wake the search's followers."""
        if self._running and self._iteration is None:
            return
        if not self._running:
            await asyncio.to_thread(self.store.update, self.sid, self.lease, status="running")
            self._running = True
        if self._iteration is not None:
            iteration, target = self._iteration
            changes = _target_changes(target)
            await asyncio.to_thread(
                self.store.add_iteration, self.sid, iteration, self.lease, **changes
            )
            self._iteration = None
        self.notifier.publish(self.sid)

    async def update(self, **changes: Unpack[SearchChanges]) -> None:
        """Change the search now (under the lease), on a worker thread."""
        await asyncio.to_thread(self.store.update, self.sid, self.lease, **changes)

    async def succeed(
        self,
        result: SearchResult,
        final: Iteration | None = None,
        target: DetectResponse | None = None,
    ) -> SearchResult:
        """Write what waits, then the search's success with ``result``: with its ``final``
        iteration (and the target's detections, when new) if that is not recorded yet. The
        search's followers are woken when its run ends."""
        await self.flush()
        if final is None:
            await self.update(status="succeeded", result=result)
        else:
            changes = _target_changes(target, status="succeeded", result=result)
            await asyncio.to_thread(
                self.store.add_iteration, self.sid, final, self.lease, **changes
            )
        return result
