"""A real renderer process shares its Mitsuba thread: a small view requested while a large render
runs is answered between two of the large render's sample passes, long before it finishes."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.support import ServiceProcess, running_service

pytestmark = pytest.mark.slow

POSE = {"theta_deg": 40.0, "phi_deg": 30.0}
LARGE = {"scene": "demo", "pose": POSE, "width": 640, "height": 480, "spp": 64}  # 19.7 M samples
SMALL = {"scene": "demo", "pose": POSE, "width": 160, "height": 120, "spp": 4}
SLICE = 1 << 20  # the large render in 19 passes of 3-4 spp


@pytest.fixture(scope="module")
def renderer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    env = {"COSMOS_RENDERER_SLICE_SAMPLES": str(SLICE)}
    with running_service("services.renderer.app:app", tmp_path_factory.mktemp("fair"), env) as s:
        yield s


def test_a_small_view_behind_a_large_render_is_answered_first(renderer, service_token):
    auth = {"Authorization": f"Bearer {service_token}"}
    with httpx.Client(base_url=renderer.url, timeout=120.0, headers=auth) as client:
        for body in (LARGE, SMALL):  # load the scene at both film sizes, record the kernels
            assert client.post("/render", json=body).status_code == 200
        done: dict[str, float] = {}

        def large() -> None:
            assert client.post("/render", json=LARGE).status_code == 200
            done["large"] = time.perf_counter()

        started = time.perf_counter()
        worker = threading.Thread(target=large)
        worker.start()
        while client.get("/health").json()["in_flight"] < 1:  # the large render is under way
            time.sleep(0.005)
        time.sleep(0.2)
        asked = time.perf_counter()
        small = client.post("/render", json=SMALL)
        done["small"] = time.perf_counter()
        worker.join()
    assert small.status_code == 200
    large_s, small_wait_s = done["large"] - started, done["small"] - asked
    assert done["small"] < done["large"], (small_wait_s, large_s)
    assert small_wait_s < large_s / 3, (small_wait_s, large_s)
