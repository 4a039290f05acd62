"""The micro-batcher alone: batches form under load, each caller's ``finish`` runs on the worker
thread after the run, and a failing ``finish`` fails only its own caller."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from services.detector.batching import MicroBatcher

pytestmark = pytest.mark.anyio


def doubled(batch: np.ndarray) -> np.ndarray:
    return batch * 2.0


async def test_rows_come_back_to_their_callers_and_batch_under_load():
    batcher = MicroBatcher(doubled, max_batch=8, window_s=0.02)
    await batcher.start()
    try:
        inputs = [np.full((3, 2, 2), i, np.float32) for i in range(6)]
        answers = await asyncio.gather(*(batcher.submit(x) for x in inputs))
        for x, (row, run_ms) in zip(inputs, answers, strict=True):
            assert np.array_equal(row, x * 2.0)
            assert run_ms >= 0.0
        assert batcher.stats.images == 6
        assert batcher.stats.batches < 6
    finally:
        await batcher.close()


async def test_finish_runs_on_the_worker_thread_and_its_errors_stay_its_own():
    batcher = MicroBatcher(doubled, max_batch=4, window_s=0.02)
    await batcher.start()
    loop_thread = threading.get_ident()
    threads: list[int] = []

    def total(row: np.ndarray) -> float:
        threads.append(threading.get_ident())
        return float(row.sum())

    def broken(row: np.ndarray) -> float:
        raise ValueError("post-processing failed")

    try:
        ones = np.ones((3, 2, 2), np.float32)
        good, bad, also_good = await asyncio.gather(
            batcher.submit(ones, total),
            batcher.submit(ones, broken),
            batcher.submit(ones * 3, total),
            return_exceptions=True,
        )
        assert good == (24.0, pytest.approx(good[1]))
        assert also_good[0] == 72.0
        assert isinstance(bad, ValueError)
        assert len(threads) == 2
        assert loop_thread not in threads
        assert batcher.stats.images == 3
    finally:
        await batcher.close()


async def test_a_failing_run_fails_every_caller_of_its_batch_and_serving_goes_on():
    runs: list[int] = []

    def first_run_fails(batch: np.ndarray) -> np.ndarray:
        runs.append(len(batch))
        if len(runs) == 1:
            raise RuntimeError("inference failed")
        return batch

    batcher = MicroBatcher(first_run_fails, max_batch=4, window_s=0.02)
    await batcher.start()
    try:
        zeros = np.zeros((3, 2, 2), np.float32)
        results = await asyncio.gather(
            *(batcher.submit(zeros) for _ in range(3)), return_exceptions=True
        )
        assert runs == [3]
        assert all(isinstance(r, RuntimeError) for r in results)
        row, _ = await batcher.submit(zeros + 1.0)
        assert np.array_equal(row, zeros + 1.0)
    finally:
        await batcher.close()
