"""The renderer's scheduler without Mitsuba: slices of a long job let a cheap job through, the
earliest deadline goes first, nothing starves, and errors and closing behave as an executor's."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import CancelledError

import pytest

from services.renderer.scheduler import Job, Scheduler, pass_seed, sample_passes, single_slice

SAMPLE_S = 1e-7  # the scheduler's first guess of a sample's cost: what the jobs below take


@pytest.fixture
def scheduler() -> Iterator[Scheduler]:
    s = Scheduler("test")
    yield s
    s.close()


def sliced(name: str, slices: int, samples: int, log: list[str]) -> Job[str]:
    """A job of ``slices`` slices of ``samples`` samples each, taking as long as announced."""
    for index in range(slices):
        yield samples
        time.sleep(samples * SAMPLE_S)
        log.append(f"{name}{index}")
    return name


def blocker(release: threading.Event) -> Job[None]:
    yield 0
    release.wait(5.0)


def test_a_cheap_job_runs_between_the_slices_of_an_expensive_one(scheduler):
    log: list[str] = []
    big = scheduler.submit(sliced("big", 20, 200_000, log), cost=20 * 200_000)  # 20 x 20 ms
    time.sleep(0.03)  # big is in its second slice
    small = scheduler.submit(sliced("small", 1, 10_000, log), cost=10_000)
    slices_done = len(log)
    assert small.result(timeout=5) == "small"
    assert big.result(timeout=5) == "big"
    assert log.index("small0") <= slices_done + 1  # right after the slice under way


def test_queued_jobs_run_earliest_deadline_first(scheduler):
    log: list[str] = []
    release = threading.Event()
    first = scheduler.submit(blocker(release), cost=0)
    expensive = scheduler.submit(sliced("expensive", 1, 1_000_000, log), cost=1_000_000)
    cheap = scheduler.submit(sliced("cheap", 1, 1_000, log), cost=1_000)
    release.set()
    for future in (first, expensive, cheap):
        future.result(timeout=5)
    assert log == ["cheap0", "expensive0"]


def test_an_expensive_job_is_not_starved_by_a_stream_of_cheap_ones(scheduler):
    """Cheap jobs arrive faster than they are served (shortest job first would never run the
    expensive one); those submitted after the expensive job's deadline wait for it."""
    log: list[str] = []
    expensive = scheduler.submit(sliced("big", 4, 100_000, log), cost=400_000)  # due in 40 ms
    cheap = []
    deadline = time.monotonic() + 2.0
    while not expensive.done() and time.monotonic() < deadline:
        for _ in range(3):
            cheap.append(scheduler.submit(sliced("v", 1, 20_000, log), cost=20_000))
        time.sleep(0.002)
    assert expensive.result(timeout=5) == "big"
    for future in cheap:
        future.result(timeout=5)
    assert time.monotonic() < deadline, "the expensive job waited for the whole stream"


def test_errors_reach_the_caller_and_the_worker_goes_on(scheduler):
    def broken() -> Job[None]:
        yield 10
        raise ValueError("slice failed")

    with pytest.raises(ValueError, match="slice failed"):
        scheduler.submit(broken(), cost=10).result(timeout=5)
    assert scheduler.submit(single_slice(lambda: 42), cost=0).result(timeout=5) == 42


def test_the_measured_rate_follows_the_slices(scheduler):
    log: list[str] = []
    scheduler.submit(sliced("x", 3, 100_000, log), cost=300_000).result(timeout=5)
    assert scheduler.slices == 3
    assert scheduler.seconds_per_sample == pytest.approx(SAMPLE_S, rel=0.5)


def test_closing_cancels_queued_jobs_after_the_slice_under_way():
    scheduler = Scheduler("closing")
    release = threading.Event()
    running = scheduler.submit(blocker(release), cost=0)
    queued = scheduler.submit(single_slice(lambda: 1), cost=0)
    time.sleep(0.02)
    closer = threading.Thread(target=scheduler.close)
    closer.start()
    release.set()
    closer.join(timeout=5)
    assert running.result(timeout=1) is None
    with pytest.raises(CancelledError):
        queued.result(timeout=1)
    with pytest.raises(RuntimeError, match="closed"):
        scheduler.submit(single_slice(lambda: 1), cost=0)


@pytest.mark.parametrize(
    ("pixels", "spp", "slice_samples", "passes"),
    [
        (320 * 240, 8, 1 << 22, [8]),
        (2048 * 2048, 16, 1 << 22, [1] * 16),
        (1024 * 1024, 10, 1 << 22, [4, 3, 3]),
        (2048 * 2048, 3, 1 << 20, [1, 1, 1]),  # at least one sample per pixel per pass
        (640 * 480, 64, 1 << 22, [13, 13, 13, 13, 12]),
    ],
)
def test_sample_passes_fit_the_slice_and_add_up(pixels, spp, slice_samples, passes):
    assert sample_passes(pixels, spp, slice_samples) == passes
    assert sum(passes) == spp


def test_pass_seeds_are_distinct_and_the_first_is_the_request_seed():
    seeds = [pass_seed(2**31 - 1, index) for index in range(64)]
    assert seeds[0] == 2**31 - 1
    assert len(set(seeds)) == 64
    assert all(0 <= seed < 2**32 for seed in seeds)
