"""The page in Chromium: prints first paint ms, long tasks and frame gaps while a search streams.

Run: ``.venv/bin/python -m benchmarks.page [--loads 5] [--searches 2]``

Starts the local stack (four processes on loopback) and Debian's Chromium (``/usr/bin/chromium``,
driven by Playwright; ``scripts/bootstrap.sh`` installs it). The browser's own
``PerformanceObserver`` measures:

* **first paint**: ``first-paint`` and ``first-contentful-paint`` of ``/`` in a fresh browser
  context each time (nothing cached), and when the page's script has drawn the new-search form;
  the goal is under 1 s;
* **while a search streams**: from the first iteration shown until the page shows the search
  finished, every long task (a task over 50 ms: the frames it blocked are over 50 ms) and the
  longest gap between two animation frames; the goal is no long task. The long tasks between
  the click on *Search* and the first iteration (the switch to the live view) are printed apart.
  The search walks the ``simple`` strategy from far away, so many iterations stream in.
  Each animation frame over 50 ms (the browser's Long Animation Frames) is printed with its
  parts: the rendering steps' time (style, layout, paint, commit) and the scripts that ran.

The page runs in the user's browser and the stack on other machines, so by default the
stack's processes are pinned to one half of this machine's cores and the browser to the other
(``os.sched_setaffinity``, inherited by the processes each starts): without that, on a 2-core
machine, every view the renderer makes takes both cores from under the browser, and the frame
gaps measure the renderer, not the page. ``--shared-cores`` measures that shared case.

For scale, a one-line static page's first paint and frame gaps are printed, idle and while the
same search runs over the API. A long task is what the page's own script costs; a frame gap with
no long task is paint work (raster and compositing, in software without a GPU) waiting for a core
while the renderer takes both to render the search's next view: the static page, with nothing to
paint, keeps its frames meanwhile.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from cosmos.launch import free_port
from cosmos.stack import Stack, local_stack
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import PoseQuery
from services.renderer.client import RendererClient

CHROMIUM = "/usr/bin/chromium"
SEARCH_OPTIONS = {
    "scene": "demo",
    "strategy": "simple",
    "start_theta_deg": "82.5",
    "start_phi_deg": "180",
}
ARGS = ["--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--disable-gpu-compositing"]
"""Chromium as on a desktop without a GPU: WebGL in software (SwiftShader), and the page
composited in software, as Chromium does where it finds no usable GPU. Compositing through
SwiftShader's GL instead (headless Chromium's default) cost 130-300 ms frame gaps here, with or
without the page's WebGL: the browser's set-up, not the page."""

OBSERVE = """
window.__perf = { paints: {}, longTasks: [], frames: [], frames50: [] };
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) window.__perf.paints[e.name] = e.startTime;
}).observe({ type: "paint", buffered: true });
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) window.__perf.longTasks.push([e.startTime, e.duration]);
}).observe({ type: "longtask", buffered: true });
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) {
    const scripts = e.scripts.map(
      (s) => `${s.invoker || s.sourceFunctionName || "?"} ${s.duration.toFixed(0)} ms`);
    const end = e.startTime + e.duration;
    const layout = e.styleAndLayoutStart ? end - e.styleAndLayoutStart : 0;
    window.__perf.frames50.push(
      [e.startTime, e.duration, end - e.renderStart, layout, scripts.join("; ")]);
  }
}).observe({ type: "long-animation-frame", buffered: true });
(function frame(t) { window.__perf.frames.push(t); requestAnimationFrame(frame); })(0);
"""


def _context(browser: Any, stack: Stack) -> Any:
    """A fresh browser context (nothing cached) observing paints, long tasks and frames, that
    holds the stack's API key."""
    context = browser.new_context(viewport={"width": 1280, "height": 1000})
    context.add_init_script(OBSERVE)
    key = json.dumps(stack.api_key)
    context.add_init_script(f"localStorage.setItem('cosmos.apiKey', {key})")
    return context


def _first_paints(browser: Any, stack: Stack, loads: int) -> list[dict[str, float]]:
    """Milliseconds from navigation to first paint, first contentful paint and the form drawn."""
    out = []
    for _ in range(loads):
        context = _context(browser, stack)
        page = context.new_page()
        page.goto(f"{stack.controller}/")
        page.wait_for_selector("#go")
        ready = page.evaluate("performance.now()")
        perf = page.evaluate("window.__perf.paints")
        nav = page.evaluate(
            "(() => { const n = performance.getEntriesByType('navigation')[0];"
            " return [n.responseEnd, n.domContentLoadedEventEnd]; })()"
        )
        resources = page.evaluate(
            "performance.getEntriesByType('resource').filter(r => r.name.includes('/assets/'))"
            ".reduce((s, r) => s + r.transferSize, 0)"
        )
        out.append(
            {
                "first_paint_ms": perf.get("first-paint", float("nan")),
                "first_contentful_paint_ms": perf.get("first-contentful-paint", float("nan")),
                "dom_content_loaded_ms": nav[1],
                "form_ms": ready,
                "asset_bytes": resources,
            }
        )
        context.close()
    return out


def _stream(browser: Any, stack: Stack, target: Path) -> dict[str, Any]:
    """One search followed live: long tasks and the longest frame gap while it streamed."""
    context = _context(browser, stack)
    page = context.new_page()
    page.goto(f"{stack.controller}/")
    page.wait_for_selector("#scene option[value=demo]", state="attached")
    page.set_input_files("#target-file", str(target))
    page.select_option("#strategy", SEARCH_OPTIONS["strategy"])
    page.fill("#start_theta_deg", SEARCH_OPTIONS["start_theta_deg"])
    page.fill("#start_phi_deg", SEARCH_OPTIONS["start_phi_deg"])
    page.wait_for_timeout(1000)  # the scene's preview and the 3D view are drawn: not streaming
    clicked = page.evaluate("performance.now()")
    wall = time.perf_counter()
    page.click("#go")
    page.wait_for_selector("#iterations tbody tr", timeout=300_000)
    streaming = page.evaluate("performance.now()")
    page.wait_for_selector("#status.succeeded, #status.failed", timeout=300_000)
    page.wait_for_timeout(500)  # the last view drawn
    ended = page.evaluate("performance.now()")
    perf = page.evaluate("window.__perf")
    rows = page.locator("#iterations tbody tr").count()
    context.close()
    switch = [d for s, d in perf["longTasks"] if clicked <= s < streaming]
    tasks = [d for s, d in perf["longTasks"] if streaming <= s <= ended]
    slow = [f for f in perf["frames50"] if streaming <= f[0] <= ended]
    frames = [t for t in perf["frames"] if streaming <= t <= ended]
    gaps = [b - a for a, b in zip(frames, frames[1:], strict=False)]
    return {
        "seconds": time.perf_counter() - wall,
        "iterations": rows,
        "switch_tasks": switch,
        "long_tasks": len(tasks),
        "longest_task_ms": max(tasks, default=0.0),
        "slow_frames": slow,
        "streaming": streaming,
        "frames": len(frames),
        "longest_frame_gap_ms": max(gaps, default=float("nan")),
        "p99_frame_gap_ms": sorted(gaps)[int(0.99 * (len(gaps) - 1))] if gaps else float("nan"),
    }


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        pass


def _blank_reference(browser: Any, loads: int) -> tuple[float, float, float]:
    """A one-line static page from a local HTTP server, for scale (what this browser on this
    machine takes for any page): its median first paint, and the longest and the median gap
    between its animation frames over 3 s of doing nothing (milliseconds)."""
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "index.html").write_text("<!doctype html><title>x</title><p>Hello</p>")
        handler = functools.partial(_Quiet, directory=tmp)
        server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), handler)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            paints: list[float] = []
            gaps: list[float] = []
            for _ in range(loads):
                context = browser.new_context()
                context.add_init_script(OBSERVE)
                page = context.new_page()
                page.goto(f"http://127.0.0.1:{server.server_address[1]}/")
                for _ in range(100):  # until it painted (a loaded machine can take seconds)
                    painted = page.evaluate("window.__perf.paints")
                    if "first-paint" in painted:
                        break
                    page.wait_for_timeout(50)
                paints.append(float(painted.get("first-paint", float("nan"))))
                if not gaps:  # the same page's animation frames for 3 s, doing nothing
                    start = page.evaluate("performance.now()")
                    page.wait_for_timeout(3000)
                    frames = [t for t in page.evaluate("window.__perf.frames") if t >= start]
                    gaps = [b - a for a, b in zip(frames, frames[1:], strict=False)]
                context.close()
        finally:
            server.shutdown()
            server.server_close()
    return statistics.median(paints), max(gaps, default=float("nan")), statistics.median(gaps)


def _static_page_during_search(browser: Any, stack: Stack, target: bytes) -> tuple[float, float]:
    """The longest and the 99th-percentile gap between animation frames (ms) of a one-line page
    that does nothing, while the same search as :func:`_stream`'s runs, submitted over the API:
    what the search's processes alone cost this browser's frames on this machine."""
    context = browser.new_context()
    context.add_init_script(OBSERVE)
    page = context.new_page()
    page.set_content("<p>Hello</p>")
    with httpx.Client(
        base_url=stack.controller,
        headers={"Authorization": f"Bearer {stack.api_key}"},
        timeout=60.0,
    ) as http:
        search = http.post(
            "/searches",
            params=SEARCH_OPTIONS,
            content=target,
            headers={"Content-Type": "image/png"},
        ).json()
        start = page.evaluate("performance.now()")
        deadline = time.monotonic() + 300
        while http.get(f"/searches/{search['id']}").json()["status"] in {"queued", "running"}:
            if time.monotonic() > deadline:
                break
            page.wait_for_timeout(500)
    frames = [t for t in page.evaluate("window.__perf.frames") if t >= start]
    context.close()
    gaps = sorted(b - a for a, b in zip(frames, frames[1:], strict=False))
    if not gaps:
        return float("nan"), float("nan")
    return gaps[-1], gaps[int(0.99 * (len(gaps) - 1))]


def _split_cores(*, shared: bool) -> tuple[set[int], set[int]]:
    """The cores for the stack and for the browser: this process's cores split in two halves
    (the stack gets the odd one out), or all of them for both when ``shared`` or only one."""
    cores = sorted(os.sched_getaffinity(0))
    if shared or len(cores) < 2:
        return set(cores), set(cores)
    half = len(cores) // 2
    return set(cores[half:]), set(cores[:half])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loads", type=int, default=5, help="cold loads of / to time")
    parser.add_argument("--searches", type=int, default=2, help="searches to follow live")
    parser.add_argument(
        "--shared-cores",
        action="store_true",
        help="let the browser and the stack share every core (default: half each)",
    )
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    stack_cores, browser_cores = _split_cores(shared=args.shared_cores)
    os.sched_setaffinity(0, stack_cores)  # the stack's processes inherit it
    with tempfile.TemporaryDirectory() as tmp, local_stack(Path(tmp)) as stack:
        os.sched_setaffinity(0, browser_cores)  # Playwright's driver and Chromium inherit it
        print(f"cores: stack {sorted(stack_cores)}, browser {sorted(browser_cores)}")
        with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
            png = renderer.render_png(RenderRequest(scene="demo", pose=PoseQuery(lat=2, lon=5)))
        target = Path(tmp) / "target.png"
        target.write_bytes(png)
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            print(f"Chromium {browser.version}, controller {stack.controller}")
            # the static page first: the browser's own warm-up is not charged to the page
            blank_paint, blank_gap, blank_median = _blank_reference(browser, args.loads)
            paints = _first_paints(browser, stack, args.loads)
            print(f"first paint, {args.loads} cold loads of / (goal: under 1000 ms):")
            for key in ("first_paint_ms", "first_contentful_paint_ms", "dom_content_loaded_ms"):
                values = [p[key] for p in paints]
                print(
                    f"  {key:<28} median {statistics.median(values):7.1f}  max {max(values):7.1f}"
                )
            forms = [p["form_ms"] for p in paints]
            print(f"  {'new-search form drawn_ms':<28} median {statistics.median(forms):7.1f}")
            print(f"  assets transferred: {paints[0]['asset_bytes'] / 1024:.0f} KiB (gzip)")
            print(f"  (a one-line static page, for scale: first paint median {blank_paint:.1f} ms)")
            print("while a search streams (goal: no frame over 50 ms, i.e. no long task):")
            for _ in range(args.searches):
                s = _stream(browser, stack, target)
                print(
                    f"  {s['iterations']:3d} iterations in {s['seconds']:5.1f} s: "
                    f"{s['long_tasks']} long tasks (longest {s['longest_task_ms']:.0f} ms), "
                    f"{s['frames']} frames, longest frame gap {s['longest_frame_gap_ms']:.1f} ms, "
                    f"p99 {s['p99_frame_gap_ms']:.1f} ms"
                )
                for at, total, render, layout, scripts in s["slow_frames"]:
                    print(
                        f"      a {total:.0f} ms frame at {(at - s['streaming']) / 1000:.1f} s: "
                        f"rendering {render:.0f} ms (style and layout on {layout:.0f} ms), "
                        f"scripts: {scripts or 'none'}"
                    )
                switch = ", ".join(f"{d:.0f}" for d in s["switch_tasks"]) or "none"
                print(f"      before the first iteration (switching to the live view): {switch} ms")
            during_gap, during_p99 = _static_page_during_search(browser, stack, png)
            print(
                "  (a one-line page doing nothing while the same search runs over the API, for "
                f"scale: longest frame gap {during_gap:.1f} ms, p99 {during_p99:.1f} ms)"
            )
            print(
                f"  (the static page idle, for scale: longest frame gap {blank_gap:.1f} ms, "
                f"median {blank_median:.1f} ms)"
            )
            browser.close()


if __name__ == "__main__":
    main()
