"""What a detection request must be granted before its image is decoded: a place among the
requests in flight, and the memory its decoded image will take.

A request count alone does not bound memory: a 130 KB PNG of 4096 x 4096 16-bit RGBA pixels
decodes to 50 MB, and 16 of them at once took the detector to 752 MB while 64 were admitted. So
each request also holds its image's :attr:`~services.common.images.ImageHeader.decoded_bytes`,
read from the header before anything is decoded, from just before the decode until its answer
is built (the RGB array lives until the detections' colours are measured). Requests whose bytes
do not fit wait their turn, first come first served, for at most ``wait_s``, then get 503 (with
``Retry-After``); an image that could never fit gets 413.
"""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from services.common.errors import PayloadTooLargeError, ServiceUnavailableError
from services.common.images import ImageHeader

__all__ = ["Admission", "DecodeBudget"]


class DecodeBudget:
    """At most ``limit_bytes`` of decoded images held at once; a request waits up to ``wait_s``
    for its bytes, in arrival order (a large image is not overtaken for ever by small ones).

    Use from one event loop: :meth:`hold` around the decode and everything that keeps its
    pixels.
    """

    def __init__(self, limit_bytes: int, wait_s: float) -> None:
        if limit_bytes < 1 or wait_s < 0.0:
            raise ValueError("limit_bytes must be positive and wait_s not negative")
        self.limit_bytes = limit_bytes
        self.wait_s = wait_s
        self.in_use = 0
        """Bytes held now."""
        self.peak = 0
        """The most bytes held at once since start."""
        self._waiting: deque[tuple[int, asyncio.Future[None]]] = deque()

    @asynccontextmanager
    async def hold(self, header: ImageHeader) -> AsyncIterator[None]:
        """Hold ``header.decoded_bytes`` for the block.

        Raises
        ------
        PayloadTooLargeError
            The image alone needs more than the whole budget.
        ServiceUnavailableError
            Its bytes did not become free within ``wait_s``.
        """
        size = header.decoded_bytes
        if size > self.limit_bytes:
            raise PayloadTooLargeError(
                f"the {header.width}x{header.height} image takes {size} bytes to decode "
                f"({header.channels} channels of {header.bit_depth} bits), more than the "
                f"detector's decode budget of {self.limit_bytes} bytes "
                "(COSMOS_DETECTOR_MAX_DECODE_BYTES)",
                field="image",
                slug="image-too-large",
                title="Image too large",
            )
        await self._acquire(size)
        try:
            yield
        finally:
            self._release(size)

    async def _acquire(self, size: int) -> None:
        if not self._waiting and self.in_use + size <= self.limit_bytes:
            self._take(size)
            return
        granted = asyncio.get_running_loop().create_future()
        entry = (size, granted)
        self._waiting.append(entry)
        try:
            # asyncio.wait leaves the future alone on a timeout or a cancellation, so whether
            # the bytes were granted meanwhile can be told afterwards.
            await asyncio.wait({granted}, timeout=self.wait_s)
        except asyncio.CancelledError:
            self._abandon(entry)
            raise
        if granted.done():
            return
        self._abandon(entry)
        raise ServiceUnavailableError(
            f"the detector holds {self.in_use} bytes of decoded images and {len(self._waiting)} "
            f"more requests wait; {size} more bytes did not fit its decode budget of "
            f"{self.limit_bytes} bytes (COSMOS_DETECTOR_MAX_DECODE_BYTES) within "
            f"{self.wait_s:g} s; try again shortly",
            slug="detector-busy",
            title="Detector busy",
        )

    def _abandon(self, entry: tuple[int, asyncio.Future[None]]) -> None:
        """A waiter leaves: give back what it was granted, or leave the queue."""
        size, granted = entry
        if granted.done():
            self._release(size)
            return
        granted.cancel()
        self._waiting.remove(entry)
        self._grant()  # the ones behind it may fit now

    def _take(self, size: int) -> None:
        self.in_use += size
        self.peak = max(self.peak, self.in_use)

    def _release(self, size: int) -> None:
        self.in_use -= size
        self._grant()

    def _grant(self) -> None:
        while self._waiting and self.in_use + self._waiting[0][0] <= self.limit_bytes:
            size, granted = self._waiting.popleft()
            self._take(size)
            granted.set_result(None)


class Admission:
    """Bounds the requests in flight across every model a service runs (each model has its own
    batcher, but decoding and queueing share the one process): at most ``limit`` requests, and
    their decoded images within ``decode`` (a :class:`DecodeBudget`)."""

    def __init__(self, limit: int, decode: DecodeBudget) -> None:
        self.limit = limit
        self.decode = decode
        self._lock = threading.Lock()
        self._in_flight = 0

    @property
    def in_flight(self) -> int:
        """Requests being decoded, waiting for or in inference, or post-processed."""
        return self._in_flight

    def admit(self) -> None:
        """Count one more request in, or refuse it with a 503 when ``limit`` are in."""
        with self._lock:
            if self._in_flight >= self.limit:
                raise ServiceUnavailableError(
                    f"the detector has {self._in_flight} requests in flight; try again shortly",
                    slug="detector-busy",
                    title="Detector busy",
                )
            self._in_flight += 1

    def release(self) -> None:
        with self._lock:
            self._in_flight -= 1
