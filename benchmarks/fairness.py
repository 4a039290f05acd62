"""How long a search view waits behind a large render, on real renderer processes.

Run: ``.venv/bin/python -m benchmarks.fairness [--large 2048x2048x16] [--view 320x240x8]``

For each configuration a renderer process is started; both film sizes are rendered once (scene
loaded, kernels compiled), and the large render alone is timed. Then the large render is
requested again and, while it runs, search views are requested one after another (each 0.3 s
after the previous answer) until it is done. Printed: the large render alone and with the views
beside it, and the views' waits: the first, the median and the longest.

"one pass" renders each request in one Mitsuba call (``COSMOS_RENDERER_SLICE_SAMPLES`` larger
than any render): the view waits for the whole large render, as every request did before the
renderer worked in slices. "sliced" is the default: the large render runs in sample passes and
the views go between them.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from cosmos.launch import running_service

POSE = {"theta_deg": 40.0, "phi_deg": 30.0}
ONE_PASS = 1 << 62


def _film(text: str) -> dict[str, int]:
    width, height, spp = (int(part) for part in text.lower().split("x"))
    return {"width": width, "height": height, "spp": spp}


def measure(large: dict[str, int], view: dict[str, int], env: dict[str, str]) -> dict[str, Any]:
    """The large render's time alone and beside views, and the views' waits, in seconds."""
    large_body = {"scene": "demo", "pose": POSE, **large}
    with tempfile.TemporaryDirectory() as logs:
        with (
            running_service("services.renderer.app:app", Path(logs), env) as renderer,
            httpx.Client(base_url=renderer.url, timeout=600.0) as client,
        ):
            client.post("/render", json={"scene": "demo", "pose": POSE, **view}).raise_for_status()
            client.post("/render", json=large_body).raise_for_status()  # load, compile
            started = time.perf_counter()
            client.post("/render", json=large_body).raise_for_status()
            alone = time.perf_counter() - started
            finished: list[float] = []

            def run_large() -> None:
                client.post("/render", json=large_body).raise_for_status()
                finished.append(time.perf_counter())

            started = time.perf_counter()
            worker = threading.Thread(target=run_large)
            worker.start()
            while client.get("/health").json()["in_flight"] < 1:
                time.sleep(0.005)
            waits = []
            phi = 0.0
            while not finished:
                time.sleep(0.3)
                phi += 7.5  # a new pose each time, as a search asks for
                body = {"scene": "demo", "pose": {"theta_deg": 30.0, "phi_deg": phi}, **view}
                asked = time.perf_counter()
                client.post("/render", json=body).raise_for_status()
                if not finished or asked < finished[0]:  # asked while the large one ran
                    waits.append(time.perf_counter() - asked)
            worker.join()
    return {"alone": alone, "beside": finished[0] - started, "waits": waits}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--large", type=_film, default=_film("2048x2048x16"))
    parser.add_argument("--view", type=_film, default=_film("320x240x8"))
    parser.add_argument(
        "--slice-samples", type=int, default=None, help="the sliced run's slice (default: its)"
    )
    args = parser.parse_args()
    one_pass = {"COSMOS_RENDERER_SLICE_SAMPLES": str(ONE_PASS)}
    sliced = {}
    if args.slice_samples is not None:
        sliced["COSMOS_RENDERER_SLICE_SAMPLES"] = str(args.slice_samples)
    large, view = args.large, args.view
    print(
        f"large {large['width']}x{large['height']} at {large['spp']} spp, views "
        f"{view['width']}x{view['height']} at {view['spp']} spp"
    )
    for name, env in (("one pass", one_pass), ("sliced", sliced)):
        result = measure(large, view, env)
        waits = result["waits"]
        print(
            f"{name:>8}: large alone {result['alone']:.1f} s, beside views "
            f"{result['beside']:.1f} s; {len(waits)} views waited: first {waits[0]:.2f} s, "
            f"median {statistics.median(waits):.2f} s, longest {max(waits):.2f} s"
        )


if __name__ == "__main__":
    main()
