"""Detector memory under a burst of large uploads: with the decode budget, and without it.

Run: ``.venv/bin/python -m benchmarks.decode_memory [--side 4096] [--burst 16]``

A real detector process (a synthetic constant model, so inference costs nothing) is sent
``--burst`` concurrent PNGs of ``--side`` x ``--side`` 16-bit RGBA pixels: small files (mostly
zeros) that each decode to ``side**2 * 3`` bytes. Printed per budget: the process's resident
memory before the burst and the most sampled during it (``/proc/<pid>/status``, every 5 ms),
the most decoded bytes the service itself counted held at once, and how long the burst took.
"Without" is a budget larger than the whole burst: only the request count bounds it, as before.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from cosmos.launch import running_service
from services.detector.synthetic import constant_model

MIB = 1 << 20


def _rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS")


def _png(side: int) -> bytes:
    image = np.zeros((side, side, 4), np.uint16)
    image[::64, ::64] = 50_000
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buffer.tobytes()


def burst(side: int, count: int, budget: int, workdir: Path) -> dict[str, Any]:
    """Resident memory of a detector process around ``count`` concurrent uploads."""
    model = constant_model(
        workdir / "constant.onnx",
        np.array([[100], [120], [40], [80], [0.9], [0.0]], np.float32),
        classes=["sphere", "cube"],
    )
    env = {
        "COSMOS_DETECTOR_MODEL": str(model),
        "COSMOS_DETECTOR_THREADS": "1",
        "COSMOS_DETECTOR_MAX_IMAGE_PIXELS": str(side * side),
        "COSMOS_DETECTOR_MAX_DECODE_BYTES": str(budget),
        "COSMOS_DETECTOR_DECODE_WAIT_S": "60",
    }
    data = _png(side)
    headers = {"content-type": "image/png"}
    with (
        running_service("services.detector.app:app", workdir / "logs", env) as service,
        httpx.Client(base_url=service.url, timeout=120.0) as client,
    ):
        pid = service.process.pid
        client.post("/detect", content=data, headers=headers).raise_for_status()  # warm
        before = peak = _rss(pid)
        done = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not done.is_set():
                peak = max(peak, _rss(pid))
                time.sleep(0.005)

        sampler = threading.Thread(target=sample)
        sampler.start()
        started = time.perf_counter()
        try:
            with ThreadPoolExecutor(count) as pool:
                answers = list(
                    pool.map(
                        lambda _: client.post("/detect", content=data, headers=headers),
                        range(count),
                    )
                )
        finally:
            done.set()
            sampler.join()
        seconds = time.perf_counter() - started
        health = client.get("/health").json()
    return {
        "png_bytes": len(data),
        "statuses": sorted({answer.status_code for answer in answers}),
        "rss_before_mib": before / MIB,
        "rss_peak_mib": peak / MIB,
        "held_peak_mib": health["decode_bytes_peak"] / MIB,
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=4096)
    parser.add_argument("--burst", type=int, default=16)
    parser.add_argument("--budget-mib", type=int, default=256, help="the budget measured")
    args = parser.parse_args()
    stated = args.side * args.side * 8
    print(
        f"{args.burst} concurrent {args.side}x{args.side} 16-bit RGBA PNGs "
        f"({stated / MIB:.0f} MiB of samples each, {args.side**2 * 3 / MIB:.0f} MiB decoded)"
    )
    runs = [("without", stated * (args.burst + 1)), ("with", args.budget_mib * MIB)]
    for name, budget in runs:
        with tempfile.TemporaryDirectory() as workdir:
            result = burst(args.side, args.burst, budget, Path(workdir))
        print(
            f"{name:>7} budget ({budget / MIB:5.0f} MiB): statuses {result['statuses']}, "
            f"RSS {result['rss_before_mib']:.0f} -> {result['rss_peak_mib']:.0f} MiB "
            f"(+{result['rss_peak_mib'] - result['rss_before_mib']:.0f}), decoded bytes held at "
            f"most {result['held_peak_mib']:.0f} MiB, {result['seconds']:.1f} s "
            f"(PNG {result['png_bytes'] / 1024:.0f} KB)"
        )


if __name__ == "__main__":
    main()
