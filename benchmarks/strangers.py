"""Uploads without a valid API key beside keyed ones, before and after a change, in one run.

Run: ``.venv/bin/python -m benchmarks.strangers [--strangers 40] [--keyed 4] [--baseline main]``

A real controller process (default body bounds: 20 MiB uploads, a budget of four, 5 s wait; no
stage runs, as none is needed to tell who may upload) is sent ``--strangers`` maximal uploads
(``POST /searches``, 20 MiB) with a wrong key, all at once, and 0.1 s later ``--keyed`` maximal
uploads with a valid key. Each client sends its body in 256 KiB pieces and stops as soon as an
answer has arrived. Printed per run: how the strangers were answered (count per status; ``none``
when the connection closed without an answer), how long their answers took (p50, max) and how
many MiB of body they had sent by then (mean); and the same for the keyed uploads, whose answer
once admitted is the app's own (415: their bytes are no image), or 503 when the budget stayed
full for the 5 s a request waits.

``--baseline REF`` (default ``main``; ``none`` to skip) measures the same on git ``REF``'s code
first (its tree extracted into a temporary directory, this file copied in, run as a child
process), so both figures come from one run on the same machine.
"""

from __future__ import annotations

import argparse
import json
import select
import socket
import statistics
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from benchmarks.baseline import describe, measure_at
from cosmos.launch import free_port, running_service
from services.controller.keys import KeyStore

MIB = 1 << 20
UPLOAD_LIMIT = 20 * MIB  # the controller's default body limit
PIECE = 256 * 1024


def _upload(host: str, port: int, key: str, body: bytes, out: list[tuple[str, float, int]]) -> None:
    """One upload of ``body`` with ``key``; appends (status or ``none``, seconds to the answer,
    body bytes sent by then) to ``out``."""
    started = time.monotonic()
    sent = 0
    status = "none"
    try:
        with socket.create_connection((host, port), timeout=60) as sock:
            sock.sendall(
                f"POST /searches?scene=demo HTTP/1.1\r\nHost: bench\r\nContent-Type: image/png"
                f"\r\nAuthorization: Bearer {key}\r\nContent-Length: {len(body)}\r\n\r\n".encode()
            )
            view = memoryview(body)
            try:
                while sent < len(body) and not select.select([sock], [], [], 0)[0]:
                    sent += sock.send(view[sent : sent + PIECE])
            except OSError:  # the server answered and closed meanwhile
                pass
            head = b""
            while b"\r\n" not in head:
                chunk = sock.recv(4096)
                if not chunk:
                    break
                head += chunk
            if head.startswith(b"HTTP/1.1 "):
                status = head.split()[1].decode()
    except OSError:
        pass
    out.append((status, time.monotonic() - started, sent))


def _summary(results: list[tuple[str, float, int]]) -> dict[str, Any]:
    times = [t for _, t, _ in results]
    return {
        "answers": dict(Counter(status for status, _, _ in results)),
        "p50_s": statistics.median(times),
        "max_s": max(times),
        "sent_mean_mib": statistics.fmean(sent for _, _, sent in results) / MIB,
    }


def measure(strangers: int, keyed: int) -> dict[str, Any]:
    """Flood a fresh controller as the module's docstring says; the figures."""
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        database = f"sqlite:///{directory}/controller.sqlite3"
        keys = KeyStore(database)
        _, key = keys.create("bench")
        keys.close()
        env = {
            "COSMOS_CONTROLLER_DATABASE_URL": database,
            **{
                f"COSMOS_CONTROLLER_{stage}_URLS": f"http://127.0.0.1:{free_port()}"
                for stage in ("RENDERER", "DETECTOR", "OPTIMIZER")
            },
        }
        body = b"\x89PNG" + bytes(UPLOAD_LIMIT - 1024)
        with running_service("services.controller.app:app", directory / "logs", env) as service:
            host, port = service.url.removeprefix("http://").split(":")
            refused: list[tuple[str, float, int]] = []
            served: list[tuple[str, float, int]] = []
            threads = [
                threading.Thread(
                    target=_upload, args=(host, int(port), "cosmos_wrong", body, refused)
                )
                for _ in range(strangers)
            ]
            threads += [
                threading.Thread(target=_upload, args=(host, int(port), key, body, served))
                for _ in range(keyed)
            ]
            for thread in threads[:strangers]:
                thread.start()
            time.sleep(0.1)
            for thread in threads[strangers:]:
                thread.start()
            for thread in threads:
                thread.join(120)
    return {"strangers": _summary(refused), "keyed": _summary(served)}


def _baseline(ref: str, argv: list[str]) -> dict[str, Any]:
    """:func:`measure` run on git ``ref``'s tree, in a child process."""
    return measure_at(ref, Path(__file__), [*argv, "--worker"])


def _line(name: str, r: dict[str, Any]) -> str:
    parts = []
    for who in ("strangers", "keyed"):
        s = r[who]
        answers = ", ".join(f"{k}: {v}" for k, v in sorted(s["answers"].items()))
        parts.append(
            f"{who} {{{answers}}} answered in p50 {s['p50_s']:.2f} s, max {s['max_s']:.2f} s, "
            f"after sending {s['sent_mean_mib']:.1f} MiB of 20 on average"
        )
    return f"  {name:<14} " + "; ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strangers", type=int, default=40, help="uploads with a wrong key")
    parser.add_argument("--keyed", type=int, default=4, help="uploads with a valid key")
    parser.add_argument("--baseline", default="main", help="git ref measured first; none: skip")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args.strangers, args.keyed)))
        return
    argv = ["--strangers", str(args.strangers), "--keyed", str(args.keyed)]
    print(f"{args.strangers} maximal uploads with a wrong key, then {args.keyed} with a valid one:")
    if args.baseline != "none":
        print(_line(describe(args.baseline), _baseline(args.baseline, argv)), flush=True)
    print(_line("this tree", measure(args.strangers, args.keyed)), flush=True)


if __name__ == "__main__":
    main()
