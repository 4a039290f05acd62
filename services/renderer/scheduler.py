"""The renderer's one worker thread, shared fairly: jobs run in slices, the most urgent first.

Mitsuba runs on one dedicated thread, so the renderer did one request at a time, first come first
served: a legal 2048 x 2048 render at 16 spp took 39 s, and a 320 x 240 search view queued behind
it waited 35 s. Here a job is a generator that does one slice of its work per step (a sample pass
of a large render, one object's silhouette of the ground truth) and yields how many samples that
slice traced; between two slices the thread takes up whichever queued job is most urgent. So a
small view waits for at most one slice of a large render, never for all of it.

Urgency is earliest deadline first, the deadline of a job being when it would have finished had
it run alone from its submission: ``submitted_at + cost x seconds_per_sample``, with ``cost`` the
samples it traces and ``seconds_per_sample`` measured from the slices run so far (a job announces
the samples of its next slice when it yields). A search view
submitted while a large render runs has the earlier deadline and goes first; a large render is
still never starved, since views submitted after its deadline come after it.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable, Generator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, TypeVar

__all__ = [
    "DEFAULT_SLICE_SAMPLES",
    "INITIAL_SECONDS_PER_SAMPLE",
    "Job",
    "Scheduler",
    "single_slice",
    "pass_seed",
    "sample_passes",
]

T = TypeVar("T")
Job = Generator[int, None, T]
"""A job in slices: each ``yield`` announces the samples the next slice will trace and lets more
urgent jobs go first; the slice runs when the job is resumed. The ``return`` value (after the
last slice, in the same step) is the job's result."""

DEFAULT_SLICE_SAMPLES = 1 << 22
"""Samples per slice of a render: a 2048 x 2048 film at 1 spp, ~0.5 s on the 2-core bench
machine (the LLVM variant traces ~10 M samples/s there)."""
INITIAL_SECONDS_PER_SAMPLE = 1e-7
"""Before any slice is measured: ~10 M samples/s, the LLVM variant on the 2-core bench machine."""
_RATE_MEMORY = 0.9  # weight of the past in the measured rate, per slice


def single_slice(fn: Callable[..., T], *args: Any, **kwargs: Any) -> Job[T]:
    """A job of one slice: ``fn(*args, **kwargs)``, not measured."""
    yield 0
    return fn(*args, **kwargs)


@dataclass(order=True)
class _Entry:
    deadline: float
    sequence: int
    job: Job[Any] = field(compare=False)
    future: Future[Any] = field(compare=False)
    started: bool = field(default=False, compare=False)
    announced: int = field(default=0, compare=False)  # samples of the slice it runs next


class Scheduler:
    """One worker thread running :data:`Job` slices, earliest deadline first.

    :meth:`submit` from any thread; the result arrives in a :class:`concurrent.futures.Future`.
    """

    def __init__(self, thread_name: str = "worker") -> None:
        self._queue: list[_Entry] = []
        self._sequence = itertools.count()
        self._ready = threading.Condition()
        self._closing = False
        self._seconds = 0.0  # decayed sums of slice durations and samples
        self._samples = 0.0
        self.slices = 0
        """Slices run since start (of those that announced samples)."""
        self._thread = threading.Thread(target=self._serve, name=thread_name, daemon=True)
        self._thread.start()

    @property
    def seconds_per_sample(self) -> float:
        """The measured cost of one sample, weighted by samples (large slices count most)."""
        if self._samples <= 0.0:
            return INITIAL_SECONDS_PER_SAMPLE
        return self._seconds / self._samples

    def submit(self, job: Job[T], cost: int) -> Future[T]:
        """Queue ``job``, whose slices trace ``cost`` samples in all."""
        future: Future[T] = Future()
        with self._ready:
            if self._closing:
                job.close()
                raise RuntimeError("the scheduler is closed")
            deadline = time.monotonic() + cost * self.seconds_per_sample
            heapq.heappush(self._queue, _Entry(deadline, next(self._sequence), job, future))
            self._ready.notify()
        return future

    def close(self) -> None:
        """Let the slice under way finish, cancel every job not done, stop the thread."""
        with self._ready:
            self._closing = True
            self._ready.notify()
        self._thread.join()

    def _serve(self) -> None:
        while True:
            with self._ready:
                while not self._queue and not self._closing:
                    self._ready.wait()
                if self._closing:
                    for entry in self._queue:
                        entry.job.close()
                        entry.future.cancel()
                    self._queue.clear()
                    return
                entry = heapq.heappop(self._queue)
            if self._step(entry):
                with self._ready:
                    heapq.heappush(self._queue, entry)

    def _step(self, entry: _Entry) -> bool:
        """Run one slice of ``entry``; whether it has more."""
        if not entry.started:
            if not entry.future.set_running_or_notify_cancel():
                entry.job.close()
                return False
            entry.started = True
        started = time.perf_counter()
        more = True
        try:
            announced = next(entry.job)
        except StopIteration as done:
            entry.future.set_result(done.value)
            more, announced = False, 0
        except BaseException as exc:  # handed to the caller, as an executor would
            entry.future.set_exception(exc)
            return False
        if entry.announced > 0:
            self.slices += 1
            elapsed = time.perf_counter() - started
            self._seconds = self._seconds * _RATE_MEMORY + elapsed
            self._samples = self._samples * _RATE_MEMORY + entry.announced
        entry.announced = announced
        return more


_SEED_STEP = 0x9E3779B9  # odd, so the passes of one render get distinct 32-bit seeds


def sample_passes(pixels: int, spp: int, slice_samples: int) -> list[int]:
    """The spp of each sample pass of a render: as few passes as keep each within
    ``slice_samples`` samples (but at least one sample per pixel each), spp split evenly.

    >>> sample_passes(320 * 240, 8, 1 << 22)
    [8]
    >>> sample_passes(2048 * 2048, 16, 1 << 22)
    [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1]
    >>> sample_passes(1024 * 1024, 10, 1 << 22)
    [4, 3, 3]
    """
    if pixels < 1 or spp < 1 or slice_samples < 1:
        raise ValueError("pixels, spp and slice_samples must be positive")
    count = min(spp, max(1, -(-pixels * spp // slice_samples)))
    base, extra = divmod(spp, count)
    return [base + 1] * extra + [base] * (count - extra)


def pass_seed(seed: int, index: int) -> int:
    """The seed of sample pass ``index`` of a render seeded ``seed``; pass 0 keeps ``seed``."""
    return (seed + index * _SEED_STEP) & 0xFFFFFFFF
