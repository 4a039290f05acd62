"""Memory and service under a flood of maximal uploads, before and after a change, in one run.

Run: ``.venv/bin/python -m benchmarks.uploads [--uploads 50] [--normal 12] [--target both]
[--baseline main]``

A real local stack (renderer, detector, optimizer, controller; :func:`cosmos.stack.local_stack`)
is sent ``--uploads`` valid PNGs of random pixels just under the upload limit (20 MiB), all at
once, while ``--normal`` ordinary searches (a 320x240 render of the demo scene) are submitted one
every ``--every-s`` seconds from the flood's start and followed to their end. ``--target``
``controller`` floods ``POST /searches`` (each upload a search), ``detector`` floods the
detector's ``POST /detect`` directly (the searches still need that detector), ``both`` runs
each. Printed per run: the flooded service's resident memory before and at its peak (VmHWM, the
kernel's own high-water mark, reset before the flood), how the uploads were answered (count per
status), how the normal searches fared (refused at submission, failed, succeeded), their
submission latency, and the controller's worst ``GET /livez`` latency during the flood (how late
its event loop was).

``--baseline REF`` (default ``main``; ``none`` to skip) measures the same on the code of git
``REF`` first: its tree is extracted (``git archive``) into a temporary directory, this file
copied in, and the measurement run there as a child process, so both figures come from one run
on the same machine. ``7edd34f`` is the code before the body bounds
(:mod:`services.common.bodies`) and the off-loop image writes.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import httpx
import numpy as np

from benchmarks.baseline import describe, measure_at
from cosmos.bench.memory import memory_of, reset_peak
from cosmos.stack import Stack, local_stack

MIB = 1 << 20
UPLOAD_LIMIT = 20 * 1024 * 1024  # the controller's and the detector's default body limit


def maximal_png(limit: int = UPLOAD_LIMIT, seed: int = 0) -> bytes:
    """A valid PNG of random RGB pixels (incompressible) between 99 % and 100 % of ``limit``."""
    rng = np.random.default_rng(seed)
    side = int(math.sqrt(limit / 3))
    while True:
        image = rng.integers(0, 256, (side, side, 3), np.uint8)
        ok, buffer = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RuntimeError("PNG encoding failed")
        if len(buffer) <= limit:
            if len(buffer) < 0.99 * limit:
                raise RuntimeError(f"{len(buffer)} bytes is not near {limit}")
            return buffer.tobytes()
        side -= 8


class PeakMemory:
    """A process's resident memory now and its peak since :meth:`reset` (``/proc``, through
    the fault suite's :func:`~cosmos.bench.faults.harness.memory_of`)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid

    def _memory(self) -> tuple[int, int]:
        memory = memory_of(self.pid)
        if memory is None:
            raise RuntimeError(f"process {self.pid} is gone")
        return memory

    def rss(self) -> int:
        return self._memory()[0]

    def reset(self) -> None:
        """Start the high-water mark over from the current resident size."""
        reset_peak(self.pid)

    def peak(self) -> int:
        return self._memory()[1]


def _target(stack: Stack) -> bytes:
    response = httpx.post(
        f"{stack.renderers[0]}/render",
        json={"scene": "demo", "pose": {"lat": 3, "lon": 5}, "spp": 8},
        headers={"Authorization": f"Bearer {stack.service_token}"},
        timeout=120.0,
    )
    response.raise_for_status()
    return response.content


async def _upload(
    session: aiohttp.ClientSession, url: str, data: bytes, headers: dict[str, str]
) -> str:
    try:
        async with session.post(url, data=data, headers=headers) as response:
            await response.read()
            return str(response.status)
    except TimeoutError:
        return "timeout"
    except aiohttp.ClientError as exc:
        return type(exc).__name__


async def _normal_search(
    session: aiohttp.ClientSession, stack: Stack, target: bytes, seed: int, deadline_s: float
) -> tuple[str, float]:
    """Submit one ordinary search and follow it: (outcome, submission seconds)."""
    headers = {"Authorization": f"Bearer {stack.api_key}", "Content-Type": "image/png"}
    started = time.perf_counter()
    for attempt in range(2):
        try:
            async with session.post(
                f"{stack.controller}/searches",
                params={"scene": "demo", "seed": str(seed)},
                data=target,
                headers=headers,
            ) as response:
                body = await response.json(content_type=None)
                submitted_s = time.perf_counter() - started
                if response.status != 202:
                    return f"refused {response.status}", submitted_s
                break
        except aiohttp.ServerDisconnectedError:
            # A kept-alive connection the controller closed (its keep-alive timeout) just as
            # it was reused: nothing was answered, so once more, as the controller's own
            # transport does. Twice is a refusal.
            if attempt:
                return "refused ServerDisconnectedError", time.perf_counter() - started
        except (TimeoutError, aiohttp.ClientError) as exc:
            return f"refused {type(exc).__name__}", time.perf_counter() - started
    search_id = body["id"]
    while time.perf_counter() - started < deadline_s:
        await asyncio.sleep(0.5)
        try:
            async with session.get(
                f"{stack.controller}/searches/{search_id}", headers=headers
            ) as response:
                status = (await response.json(content_type=None)).get("status")
        except (TimeoutError, aiohttp.ClientError):
            continue  # a kept-alive connection the server closed meanwhile: ask again
        if status in {"succeeded", "failed", "cancelled"}:
            return status, submitted_s
    return "unfinished", submitted_s


async def _livez(stack: Stack, stop: asyncio.Event) -> list[float]:
    """``GET /livez`` latencies of the controller, one every 0.1 s until ``stop``."""
    latencies = []
    async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=60)) as session:
        while not stop.is_set():
            started = time.perf_counter()
            try:
                async with session.get(f"{stack.controller}/livez") as response:
                    await response.read()
            except (TimeoutError, aiohttp.ClientError):
                pass
            latencies.append(time.perf_counter() - started)
            await asyncio.sleep(0.1)
    return latencies


async def _flood(stack: Stack, target_kind: str, args: argparse.Namespace) -> dict[str, Any]:
    data = maximal_png()
    target = _target(stack)
    if target_kind == "controller":
        url = f"{stack.controller}/searches?scene=demo"
        headers = {"Authorization": f"Bearer {stack.api_key}", "Content-Type": "image/png"}
        flooded = stack.processes[-1]
    else:
        url = f"{stack.detectors[0]}/detect"
        headers = {"Authorization": f"Bearer {stack.service_token}", "Content-Type": "image/png"}
        flooded = next(p for p in stack.processes if p.url == stack.detectors[0])
    memory = PeakMemory(flooded.process.pid)
    controller = PeakMemory(stack.processes[-1].process.pid)
    timeout = aiohttp.ClientTimeout(total=300)
    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(timeout=timeout, connector=connector) as session:
        # One normal search first: everything warm, the figures below are the flood's.
        warm, _ = await _normal_search(session, stack, target, 0, 120.0)
        before = memory.rss()
        memory.reset()
        controller.reset()
        stop = asyncio.Event()
        livez = asyncio.create_task(_livez(stack, stop))
        started = time.perf_counter()
        uploads = [
            asyncio.create_task(_upload(session, url, data, headers)) for _ in range(args.uploads)
        ]
        normals = []
        for i in range(args.normal):
            normals.append(
                asyncio.create_task(_normal_search(session, stack, target, i + 1, 240.0))
            )
            await asyncio.sleep(args.every_s)
        statuses = await asyncio.gather(*uploads)
        flood_s = time.perf_counter() - started
        stop.set()
        lags = await livez
        outcomes = await asyncio.gather(*normals)
    submit_s = sorted(s for _, s in outcomes)
    return {
        "target": target_kind,
        "warm_search": warm,
        "upload_bytes": len(data),
        "rss_before_mib": before / MIB,
        "rss_peak_mib": memory.peak() / MIB,
        "controller_peak_mib": controller.peak() / MIB,
        "uploads": dict(sorted(Counter(statuses).items())),
        "flood_s": flood_s,
        "normal": dict(sorted(Counter(o for o, _ in outcomes).items())),
        "normal_submit_p50_s": submit_s[len(submit_s) // 2] if submit_s else None,
        "normal_submit_max_s": submit_s[-1] if submit_s else None,
        "livez_max_s": max(lags) if lags else None,
    }


def measure(target_kind: str, args: argparse.Namespace) -> dict[str, Any]:
    """One flood of ``target_kind`` on a fresh local stack."""
    with tempfile.TemporaryDirectory() as workdir, local_stack(Path(workdir)) as stack:
        return asyncio.run(_flood(stack, target_kind, args))


def _baseline(ref: str, target_kind: str, argv: list[str]) -> dict[str, Any]:
    """:func:`measure` run on git ``ref``'s tree, in a child process."""
    return measure_at(ref, Path(__file__), [*argv, "--worker", target_kind])


def _line(name: str, r: dict[str, Any]) -> str:
    outcomes = Counter(r["normal"])
    refused = {k: v for k, v in outcomes.items() if k.startswith("refused")}
    normal = (
        f"{sum(outcomes.values())} submitted, refused {sum(refused.values())}, failed "
        f"{outcomes['failed']}, succeeded {outcomes['succeeded']}"
    )
    if outcomes["unfinished"]:
        normal += f", unfinished {outcomes['unfinished']}"
    if refused:
        normal += " (" + ", ".join(f"{k} {v}" for k, v in refused.items()) + ")"
    uploads = ", ".join(f"{k}: {v}" for k, v in r["uploads"].items())
    controller = ""
    if r["target"] != "controller":
        controller = f"; controller peak {r['controller_peak_mib']:.0f} MiB"
    return (
        f"  {name:<12} {r['target']} RSS {r['rss_before_mib']:.0f} -> peak "
        f"{r['rss_peak_mib']:.0f} MiB{controller}; uploads answered {{{uploads}}} in "
        f"{r['flood_s']:.1f} s; normal searches: {normal} (submit p50 "
        f"{r['normal_submit_p50_s']:.2f} s, max {r['normal_submit_max_s']:.2f} s); "
        f"controller /livez worst {r['livez_max_s']:.2f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uploads", type=int, default=50)
    parser.add_argument("--normal", type=int, default=12)
    parser.add_argument("--every-s", type=float, default=0.5)
    parser.add_argument("--target", choices=["controller", "detector", "both"], default="both")
    parser.add_argument("--baseline", default="main", help="git ref measured first; none: skip")
    parser.add_argument("--worker", help=argparse.SUPPRESS)  # one measurement, as JSON
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args.worker, args)))
        return
    argv = ["--uploads", str(args.uploads), "--normal", str(args.normal)]
    argv += ["--every-s", str(args.every_s)]
    kinds = ["controller", "detector"] if args.target == "both" else [args.target]
    print(
        f"{args.uploads} maximal uploads at once (PNG of random pixels, just under "
        f"{UPLOAD_LIMIT / MIB:.0f} MiB) and {args.normal} normal searches, one every "
        f"{args.every_s:g} s"
    )
    for kind in kinds:
        if args.baseline != "none":
            print(_line(describe(args.baseline), _baseline(args.baseline, kind, argv)), flush=True)
        print(_line("this tree", measure(kind, args)), flush=True)


if __name__ == "__main__":
    main()
