"""The decode budget in a real detector process: a burst of large 16-bit RGBA uploads is
answered, and the process's resident memory grows by no more than the budget."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import cv2
import httpx
import numpy as np
import pytest

from cosmos.bench.memory import memory_of
from tests.detector.conftest import APP, one_sphere_model
from tests.support import ServiceProcess, running_service

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/<pid>/status"),
]

SIDE = 2048
BUDGET = 40 << 20  # one 2048 x 2048 16-bit RGBA image (32 MiB of samples) at a time
BURST = 16


def rss_bytes(pid: int) -> int:
    memory = memory_of(pid)
    if memory is None:
        raise RuntimeError(f"no memory for process {pid}")
    return memory.rss_bytes


def rgba16_png() -> bytes:
    image = np.zeros((SIDE, SIDE, 4), np.uint16)
    image[::64, ::64] = 50_000
    ok, buffer = cv2.imencode(".png", image)
    assert ok
    return buffer.tobytes()


@pytest.fixture(scope="module")
def detector(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    directory = tmp_path_factory.mktemp("detector-memory")
    model = one_sphere_model(directory)
    env = {
        "COSMOS_DETECTOR_MODEL": str(model),
        "COSMOS_DETECTOR_THREADS": "1",
        "COSMOS_DETECTOR_MAX_IMAGE_PIXELS": str(SIDE * SIDE),
        "COSMOS_DETECTOR_MAX_DECODE_BYTES": str(BUDGET),
        "COSMOS_DETECTOR_DECODE_WAIT_S": "30",
    }
    with running_service(APP, directory / "logs", env) as service:
        yield service


def test_a_burst_of_large_uploads_grows_memory_by_at_most_the_budget(detector, service_token):
    data = rgba16_png()
    assert len(data) < 200_000  # small uploads, large images: 12.6 MB decoded, 32 MiB stated

    def post(client: httpx.Client) -> int:
        headers = {"content-type": "image/png", "authorization": f"Bearer {service_token}"}
        return client.post("/detect", content=data, headers=headers).status_code

    pid = detector.process.pid
    with httpx.Client(base_url=detector.url, timeout=60.0) as client:
        assert post(client) == 200  # warm: the first decode's buffers stay with the allocator
        before = rss_bytes(pid)
        peak = before
        done = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not done.is_set():
                peak = max(peak, rss_bytes(pid))
                time.sleep(0.005)

        sampler = threading.Thread(target=sample)
        sampler.start()
        try:
            with ThreadPoolExecutor(BURST) as pool:
                statuses = list(pool.map(lambda _: post(client), range(BURST)))
        finally:
            done.set()
            sampler.join()
        health = client.get("/health").json()
    assert statuses == [200] * BURST
    assert health["decode_bytes_peak"] <= BUDGET
    assert health["decode_bytes"] == 0
    # Without the budget all 16 decoded images (12 MiB each) were held at once: RSS grew by
    # 191 MiB (the retired benchmarks.decode_memory, docs/HISTORY.md). With it, one
    # at a time, plus what the allocator keeps of freed arrays.
    decoded = SIDE * SIDE * 3
    assert peak - before < BUDGET + 2 * decoded, (before, peak)
