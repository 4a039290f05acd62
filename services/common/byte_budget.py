"""A first-come-first-served budget of bytes for one event loop.

Used twice: request bodies in flight (:mod:`services.common.bodies`) and the detector's decoded
images (:mod:`services.detector.admission`). A caller takes ``size`` bytes, waiting up to
``wait_s`` when they do not fit, and gives them back when done. Waiters are served in arrival
order: a large request is not overtaken for ever by smaller ones (a head-of-line wait is the
price: a small request behind a large one waits for it).
"""

from __future__ import annotations

import asyncio
from collections import deque

__all__ = ["ByteBudget"]


class ByteBudget:
    """At most ``limit_bytes`` held at once. Use from one event loop."""

    def __init__(self, limit_bytes: int) -> None:
        if limit_bytes < 1:
            raise ValueError("limit_bytes must be positive")
        self.limit_bytes = limit_bytes
        self.in_use = 0
        """Bytes held now."""
        self.peak = 0
        """The most bytes held at once since start."""
        self._waiting: deque[tuple[int, asyncio.Future[None]]] = deque()

    @property
    def waiting(self) -> int:
        """Callers waiting for their bytes."""
        return len(self._waiting)

    async def acquire(self, size: int, wait_s: float) -> bool:
        """Take ``size`` bytes, waiting up to ``wait_s`` for them; False if they did not come
        (nothing is then held). A cancelled wait holds nothing either."""
        if not self._waiting and self.in_use + size <= self.limit_bytes:
            self._take(size)
            return True
        granted = asyncio.get_running_loop().create_future()
        entry = (size, granted)
        self._waiting.append(entry)
        try:
            # asyncio.wait leaves the future alone on a timeout or a cancellation, so whether
            # the bytes were granted meanwhile can be told afterwards.
            await asyncio.wait({granted}, timeout=wait_s)
        except asyncio.CancelledError:
            self._abandon(entry)
            raise
        if granted.done():
            return True
        self._abandon(entry)
        return False

    def release(self, size: int) -> None:
        """Give back ``size`` bytes taken by :meth:`acquire`."""
        self.in_use -= size
        self._grant()

    def _abandon(self, entry: tuple[int, asyncio.Future[None]]) -> None:
        """A waiter leaves: give back what it was granted, or leave the queue."""
        size, granted = entry
        if granted.done():
            self.release(size)
            return
        granted.cancel()
        self._waiting.remove(entry)
        self._grant()  # the ones behind it may fit now

    def _take(self, size: int) -> None:
        self.in_use += size
        self.peak = max(self.peak, self.in_use)

    def _grant(self) -> None:
        while self._waiting and self.in_use + self._waiting[0][0] <= self.limit_bytes:
            size, granted = self._waiting.popleft()
            self._take(size)
            granted.set_result(None)
