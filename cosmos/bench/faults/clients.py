"""The faults that come from clients, through the real processes of a :class:`~.rig.Rig` under
load (:class:`~.under_load.UnderLoad`): half-sent requests held open, maximal uploads all at
once, and one tenant asking for another's searches."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import replace
from typing import Final

import cv2
import httpx
import numpy as np

from cosmos.bench.faults.harness import (
    Load,
    count,
    p95,
)
from cosmos.bench.faults.results import MaximalUploads, SlowClients, Tenants
from cosmos.bench.faults.rig import Rig
from cosmos.bench.faults.under_load import Timing, UnderLoad, listed
from cosmos.bench.target import Target
from services.common.auth import bearer
from services.common.client import in_pieces
from services.common.http import PROBLEM_JSON
from services.common.images import PPM_MEDIA_TYPE, decode_image, encode_ppm
from services.controller.settings import ControllerSettings

__all__ = [
    "maximal_upload_body",
    "maximal_uploads",
    "slow_clients",
    "tenants",
    "well_answered",
]

MAX_SLOW_SOCKETS: Final = 1000
HALF_HEAD: Final = (
    b"POST /searches HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\nX-Slow: "
)


def _address(url: str) -> tuple[str, int]:
    host, port = url.removeprefix("http://").split(":")
    return host, int(port)


def slow_clients(rig: Rig, timing: Timing) -> SlowClients:
    """``slow_sockets`` connections to the controller (loopback only) that send part of a
    request head and then nothing (one in ten sends nothing at all, one in ten trickles a byte a
    second), held for ``slow_hold_s`` once all are open, while the load runs and ``GET /health``
    is asked every 0.2 s on a new connection. The window ends with the hold; by then the server
    should have closed every one of them (its head deadline is 10 s)."""
    host, port = _address(rig.controller_url)
    if host not in {"127.0.0.1", "localhost", "::1"}:
        raise ValueError("slow clients are sent to a loopback address only")
    if not 0 < timing.slow_sockets <= MAX_SLOW_SOCKETS:
        raise ValueError(f"slow_sockets must be 1..{MAX_SLOW_SOCKETS}")
    with UnderLoad(rig, timing, "slow-clients", seed=4000) as run:
        run.warm()
        run.begin()
        sockets: list[socket.socket] = []
        checks: list[float | None] = []  # seconds per /health answered 200, None otherwise
        holding = threading.Event()
        holding.set()

        def trickle(slow: list[socket.socket]) -> None:
            while holding.is_set():
                for sock in slow:
                    try:
                        sock.send(b"a")
                    except OSError:
                        pass
                time.sleep(1.0)

        def probe() -> None:
            while holding.is_set():
                asked = time.perf_counter()
                try:
                    ok = httpx.get(f"{rig.controller_url}/health", timeout=5.0).status_code == 200
                except httpx.TransportError:
                    ok = False
                checks.append(time.perf_counter() - asked if ok else None)
                time.sleep(0.2)

        try:
            for i in range(timing.slow_sockets):
                sock = socket.create_connection((host, port), timeout=5.0)
                sockets.append(sock)
                if i % 10:
                    sock.sendall(HALF_HEAD)
            threads = [
                threading.Thread(target=trickle, args=(sockets[5::10],), daemon=True),
                threading.Thread(target=probe, daemon=True),
            ]
            for thread in threads:
                thread.start()
            time.sleep(timing.slow_hold_s)
            holding.clear()
            for thread in threads:
                thread.join()
            closed = sum(_closed(sock) for sock in sockets)
        finally:
            holding.clear()
            for sock in sockets:
                sock.close()
        run.end()
        measured = run.finish()
    answered = [seconds for seconds in checks if seconds is not None]
    return SlowClients(
        measured,
        sockets=len(sockets),
        closed_by_server=closed,
        health_checks=len(checks),
        health_failures=len(checks) - len(answered),
        health_p95_s=p95(answered),
    )


def _closed(sock: socket.socket) -> bool:
    """Whether the server has closed the connection (after a 408 or without a word)."""
    sock.setblocking(False)
    try:
        while sock.recv(65536):
            pass  # the 408 it sent first
    except BlockingIOError:
        return False  # nothing more to read, and still open
    except OSError:
        return True  # reset
    return True


def maximal_upload_body(target: Target, limit_bytes: int, max_pixels: int, max_side: int) -> bytes:
    """A valid image of the target's view just under ``limit_bytes``: the target scaled up
    (same aspect) to the largest binary PPM that fits, ``P6`` header plus 3 bytes a pixel, so
    nothing compresses it, within the controller's caps of ``max_pixels`` and ``max_side``."""
    rgb = decode_image(target.image, max_pixels=1 << 24, max_side=1 << 14)
    height, width = rgb.shape[:2]
    pixels = min((limit_bytes - 32) // 3, max_pixels)
    new_width = min(int((pixels * width / height) ** 0.5), max_side)
    new_height = min(pixels // new_width, max_side)
    scaled = cv2.resize(rgb, (new_width, new_height), interpolation=cv2.INTER_LINEAR)
    body = encode_ppm(np.ascontiguousarray(scaled))
    if len(body) > limit_bytes:
        raise RuntimeError(f"{len(body)} bytes do not fit under {limit_bytes}")
    return body


def _controller_setting(rig: Rig, name: str) -> int:
    """The controller's integer setting ``controller_<name>`` as the rig runs it."""
    default = ControllerSettings.model_fields[f"controller_{name}"].default
    return int(rig.setting(f"COSMOS_CONTROLLER_{name.upper()}", str(default)))


def maximal_uploads(rig: Rig, timing: Timing) -> MaximalUploads:
    """``uploads`` clients of one tenant key each send a maximal target
    (:func:`maximal_upload_body`) at once, while the load runs. Every upload must get an answer:
    202, or a 4xx problem, or 503 with ``Retry-After``; never another 5xx or none. The searches
    the uploads started are cancelled once all are answered (they are not the load). The
    window runs from the first upload to the last answer; the controller's peak memory is the
    figure to watch."""
    limit = _controller_setting(rig, "max_upload_bytes")
    body = maximal_upload_body(
        rig.targets[0],
        limit,
        _controller_setting(rig, "max_image_pixels"),
        _controller_setting(rig, "max_image_side"),
    )
    uploader = rig.new_key("uploads")
    with UnderLoad(rig, timing, "maximal-uploads", seed=5000) as run:
        run.warm()
        started = run.begin()
        ready = threading.Barrier(timing.uploads)
        answers: list[tuple[int | None, bool, float, str | None]] = []
        errors: Counter[str] = Counter()  # what the client saw of those unanswered
        errors_lock = threading.Lock()

        with httpx.Client(
            base_url=rig.controller_url,
            timeout=httpx.Timeout(timing.upload_timeout_s, connect=10.0),
            limits=httpx.Limits(max_connections=timing.uploads),
            headers={**bearer(uploader), "Content-Type": PPM_MEDIA_TYPE},
        ) as client:

            def upload(_: int) -> tuple[int | None, bool, float, str | None]:
                ready.wait(timeout=timing.upload_timeout_s)
                try:
                    response = client.post(
                        "/searches",
                        content=in_pieces(body),  # whole, the client starved itself
                        params={"scene": "demo"},
                        headers={"Content-Length": str(len(body))},  # not chunked on the wire
                    )
                except httpx.TransportError as error:
                    with errors_lock:
                        errors[f"{type(error).__name__}: {error}"] += 1
                    return None, False, time.monotonic() - started, None
                return (
                    response.status_code,
                    well_answered(response),
                    time.monotonic() - started,
                    response.json().get("id") if response.status_code == 202 else None,
                )

            with ThreadPoolExecutor(timing.uploads) as pool:
                answers = list(pool.map(upload, range(timing.uploads)))
            run.end()
            for _, _, _, search_id in answers:
                if search_id is not None:
                    client.delete(f"/searches/{search_id}")
        measured = run.finish()
    statuses: dict[int, int] = {}
    for status, _, _, _ in answers:
        if status is not None:
            statuses[status] = statuses.get(status, 0) + 1
    return MaximalUploads(
        measured,
        uploads=timing.uploads,
        body_bytes=len(body),
        limit_bytes=limit,
        statuses=statuses,
        unanswered=sum(status is None for status, _, _, _ in answers),
        transport_errors=dict(errors),
        badly_answered=sum(status is not None and not good for status, good, _, _ in answers),
        slowest_answer_s=max((seconds for _, _, seconds, _ in answers), default=0.0),
    )


def well_answered(response: httpx.Response) -> bool:
    """202, or a problem (4xx, or 503 with ``Retry-After``; 429 with it too)."""
    status = response.status_code
    if status == 202:
        return True
    if not (400 <= status < 500 or status == 503):
        return False
    problem = response.headers.get("content-type", "").startswith(PROBLEM_JSON)
    return problem and (status not in {429, 503} or "retry-after" in response.headers)


class _Peeker:
    """One tenant's requests for another's searches, counting those that are not hidden as an
    unknown id is (a 404 of the same type and title)."""

    def __init__(self, url: str, key: str) -> None:
        self._client = httpx.Client(base_url=url, timeout=30.0, headers=bearer(key))
        unknown = self._client.get("/searches/no-such-search").json()
        self._unknown = (unknown["type"], unknown["title"])
        self.requests = 0
        self.seen = 0

    def __enter__(self) -> _Peeker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._client.close()

    def peek(self, search_id: str, *methods: str) -> None:
        for method in methods:
            answer = self._client.request(method, f"/searches/{search_id}")
            body = answer.json()
            hidden = answer.status_code == 404 and (body.get("type"), body.get("title")) == (
                self._unknown
            )
            self.requests += 1
            self.seen += not hidden


def tenants(rig: Rig, timing: Timing) -> Tenants:
    """Two tenant keys, A (the load) and B (one client of its own), search side by side. Mid-load
    B asks for and tries to cancel A's searches in flight, and A asks for B's; afterwards each
    asks for every search of the other, B tries to cancel each of A's, and both list theirs.
    Every such request must be a 404 like an unknown id's, and no list may hold the other's."""
    key_a, key_b = rig.new_key("tenant-a"), rig.new_key("tenant-b")
    with UnderLoad(rig, timing, "tenants", seed=6000, key=key_a) as run, ExitStack() as stack:
        other = Load(rig.controller_url, key_b, rig.targets, concurrency=1, first_seed=6500)
        stack.callback(other.halt, 0.0)
        other.start()
        b_peeks = stack.enter_context(_Peeker(rig.controller_url, key_b))
        a_peeks = stack.enter_context(_Peeker(rig.controller_url, key_a))
        run.warm()
        run.begin()
        deadline = time.monotonic() + max(timing.after_s, 2.0)
        while time.monotonic() < deadline:  # while searches of both run
            for search_id in run.load.in_flight:
                b_peeks.peek(search_id, "GET", "DELETE")
            for search_id in other.in_flight:
                a_peeks.peek(search_id, "GET")
            time.sleep(0.1)
        run.end()
        measured = run.finish()
        theirs = other.stop(timing.drain_s)
        ids_a = {o.search_id for o in run.outcomes if o.search_id is not None}
        ids_b = {o.search_id for o in theirs if o.search_id is not None}
        for search_id in ids_a:
            b_peeks.peek(search_id, "GET", "DELETE")
        for search_id in ids_b:
            a_peeks.peek(search_id, "GET")
    listed_a, listed_b = listed(rig.controller_url, key_a), listed(rig.controller_url, key_b)
    everyone = [*run.outcomes, *theirs]
    return Tenants(
        replace(
            measured,
            counts=count(everyone),
            errors=tuple(sorted({str(o.error) for o in everyone if o.lost})),
        ),
        a_searches=len(ids_a),
        b_searches=len(ids_b),
        checks=b_peeks.requests + a_peeks.requests + 2,
        b_saw_a=b_peeks.seen + len(ids_a & listed_b.keys()),
        a_saw_b=a_peeks.seen + len(ids_b & listed_a.keys()),
        b_lists_own=ids_b <= listed_b.keys(),
    )
