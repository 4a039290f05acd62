"""A small async micro-batcher: concurrent requests share one inference run.

Every image waits in one queue; a single consumer takes the first, lets up to ``window_s`` pass
for company (only when it is alone and batching is possible), takes whatever else is queued up to
``max_batch``, and runs the batch on one dedicated worker thread. While a batch runs, new requests
queue up and form the next batch, so under load batches fill without any added wait; a lone
request pays at most ``window_s``. With ``max_batch = 1`` (a model of fixed batch size 1) it is
a plain serial queue: one run at a time, each using all of onnxruntime's threads.

Each request may hand in a ``finish`` function of its output row (post-processing); it runs on
the worker thread right after the batch, so a request crosses threads once, not twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["BatchStats", "MicroBatcher"]

Run = Callable[[NDArray[np.float32]], NDArray[np.float32]]
Finish = Callable[[NDArray[np.float32]], Any]


@dataclass
class BatchStats:
    """Counters since start: runs, images run, and the largest batch."""

    batches: int = 0
    images: int = 0
    largest: int = 0


def _identity(row: NDArray[np.float32]) -> NDArray[np.float32]:
    return row


@dataclass
class _Item:
    tensor: NDArray[np.float32]
    finish: Finish
    future: asyncio.Future[tuple[Any, float]] = field(repr=False)


class MicroBatcher:
    """Batches ``(3, H, W)`` inputs into ``run((B, 3, H, W)) -> (B, ...)`` calls.

    Use inside a running event loop: :meth:`start`, then :meth:`submit` from any number of
    tasks, then :meth:`close`.
    """

    def __init__(self, run: Run, *, max_batch: int, window_s: float = 0.0) -> None:
        if max_batch < 1 or window_s < 0.0:
            raise ValueError("max_batch must be at least 1 and window_s not negative")
        self._run = run
        self.max_batch = max_batch
        self._window_s = window_s
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inference")
        self._queue: asyncio.Queue[_Item] | None = None
        self._task: asyncio.Task[None] | None = None
        self.stats = BatchStats()

    async def start(self) -> None:
        """Start the consumer on the running loop."""
        self._queue = asyncio.Queue()
        self._task = asyncio.create_task(self._serve(self._queue), name="micro-batcher")

    async def close(self) -> None:
        """Stop the consumer, fail whatever still waits, and stop the worker thread."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self._queue is not None:
            while not self._queue.empty():
                item = self._queue.get_nowait()
                if not item.future.done():
                    item.future.set_exception(RuntimeError("the detector is shutting down"))
        self._executor.shutdown(wait=True, cancel_futures=True)

    async def submit(
        self, tensor: NDArray[np.float32], finish: Finish = _identity
    ) -> tuple[Any, float]:
        """``finish(row)`` of this input's output row (the row itself by default), and the
        duration of the run that produced it in ms. ``finish`` runs on the worker thread; what
        it raises is raised here."""
        if self._queue is None or self._task is None or self._task.done():
            raise RuntimeError("the batcher is not running")
        future: asyncio.Future[tuple[Any, float]] = asyncio.get_running_loop().create_future()
        self._queue.put_nowait(_Item(tensor, finish, future))
        return await future

    async def _serve(self, queue: asyncio.Queue[_Item]) -> None:
        loop = asyncio.get_running_loop()
        while True:
            items = [await queue.get()]
            if self.max_batch > 1 and self._window_s > 0.0 and queue.empty():
                await asyncio.sleep(self._window_s)
            while len(items) < self.max_batch and not queue.empty():
                items.append(queue.get_nowait())
            items = [item for item in items if not item.future.done()]  # callers that left
            if not items:
                continue
            try:
                results = await loop.run_in_executor(self._executor, self._run_batch, items)
            except Exception as exc:  # handed to every caller of this batch
                for item in items:
                    if not item.future.done():
                        item.future.set_exception(exc)
                continue
            self.stats.batches += 1
            self.stats.images += len(items)
            self.stats.largest = max(self.stats.largest, len(items))
            for item, result in zip(items, results, strict=True):
                if item.future.done():
                    continue
                if isinstance(result, BaseException):
                    item.future.set_exception(result)
                else:
                    item.future.set_result(result)

    def _run_batch(self, items: list[_Item]) -> list[tuple[Any, float] | Exception]:
        """On the worker thread: one run for the batch, then each item's ``finish``."""
        started = time.perf_counter()
        outputs = self._run(np.stack([item.tensor for item in items]))
        if outputs.shape[0] != len(items):
            raise RuntimeError(
                f"the model returned {outputs.shape[0]} outputs for {len(items)} inputs"
            )
        run_ms = (time.perf_counter() - started) * 1000.0
        results: list[tuple[Any, float] | Exception] = []
        for row, item in enumerate(items):
            try:
                results.append((item.finish(outputs[row]), run_ms))
            except Exception as exc:  # this caller's post-processing failed, not the batch
                results.append(exc)
        return results
