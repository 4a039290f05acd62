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

import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from services.common.byte_budget import ByteBudget
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
        self._bytes = ByteBudget(limit_bytes)

    @property
    def in_use(self) -> int:
        """Bytes held now."""
        return self._bytes.in_use

    @property
    def peak(self) -> int:
        """The most bytes held at once since start."""
        return self._bytes.peak

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
        if await self._bytes.acquire(size, self.wait_s):
            return
        raise ServiceUnavailableError(
            f"the detector holds {self.in_use} bytes of decoded images and "
            f"{self._bytes.waiting} more requests wait; {size} more bytes did not fit its decode "
            f"budget of {self.limit_bytes} bytes (COSMOS_DETECTOR_MAX_DECODE_BYTES) within "
            f"{self.wait_s:g} s; try again shortly",
            slug="detector-busy",
            title="Detector busy",
        )

    def _release(self, size: int) -> None:
        self._bytes.release(size)


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
