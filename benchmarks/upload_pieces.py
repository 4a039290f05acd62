"""Large uploads from one process at once, the body handed to httpx whole or in pieces.

Run: ``.venv/bin/python -m benchmarks.upload_pieces [--uploads 50] [--mib 48] [--hold 2]``

A sink server (a process of its own, so that it takes none of the clients' GIL) reads each
request's head, notes when it came, answers 503 after ``--hold`` seconds (as the controller's
full body budget does, later than that), then reads and drops the body. ``--uploads`` threads of
one ``httpx.Client`` each post ``--mib`` MiB at once, first as one ``bytes``, then in pieces
(:func:`services.common.client.in_pieces`, ``Content-Length`` set). It prints, per way, the
clients' CPU time, when the last request head reached the server after the threads were let go
(a service closes a connection whose head has not come within 10 s), the wall time and the
answers, then the ratios.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import httpx

from cosmos.launch import free_port
from services.common.client import in_pieces

ANSWER = b"HTTP/1.1 503 Service Unavailable\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"


@dataclass(frozen=True)
class Way:
    """One way of handing the body over, as measured."""

    name: str
    uploads: int
    answered: int
    cpu_s: float
    last_head_s: float
    wall_s: float


async def _sink(port: int, hold_s: float, heads: Path) -> None:
    arrivals: list[float] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await reader.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, ConnectionError):  # a probe: no request
            writer.close()
            return
        arrivals.append(time.time())
        heads.write_text("\n".join(map(repr, arrivals)))
        await asyncio.sleep(hold_s)
        writer.write(ANSWER)
        await writer.drain()
        while await reader.read(1 << 18):  # the body, dropped
            pass
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", port, backlog=1024)
    async with server:
        await server.serve_forever()


def _upload_all(url: str, body: bytes, uploads: int, pieces: bool) -> tuple[int, float, float]:
    """Answers, the time the threads were let go (epoch seconds), and the wall seconds."""
    ready = threading.Barrier(uploads)
    let_go: list[float] = []
    headers = {"Content-Length": str(len(body))} if pieces else {}
    with httpx.Client(
        base_url=url, timeout=120.0, limits=httpx.Limits(max_connections=uploads)
    ) as client:

        def upload(_: int) -> bool:
            ready.wait()
            if not let_go:
                let_go.append(time.time())
            content = in_pieces(body) if pieces else body
            try:
                return client.post("/", content=content, headers=headers).status_code == 503
            except httpx.TransportError:
                return False

        started = time.monotonic()
        with ThreadPoolExecutor(uploads) as pool:
            answered = sum(pool.map(upload, range(uploads)))
        return answered, let_go[0], time.monotonic() - started


def measure(uploads: int, mib: float, hold_s: float) -> list[Way]:
    """Both ways against one sink server, whole first."""
    body = b"\0" * int(mib * (1 << 20))
    port = free_port()
    ways = []
    with tempfile.TemporaryDirectory() as tmp:
        heads = Path(tmp) / "heads"
        command = [sys.executable, "-m", "benchmarks.upload_pieces", "--serve", str(port)]
        sink = subprocess.Popen([*command, "--hold", str(hold_s), "--heads", str(heads)])
        try:
            _wait_for(port)
            for name, pieces in (("whole", False), ("in pieces", True)):
                heads.write_text("")
                cpu = time.process_time()
                answered, let_go, wall_s = _upload_all(
                    f"http://127.0.0.1:{port}", body, uploads, pieces
                )
                cpu_s = time.process_time() - cpu
                arrivals = [float(line) for line in heads.read_text().split()]
                last = max(arrivals, default=let_go) - let_go
                ways.append(Way(name, uploads, answered, cpu_s, last, wall_s))
        finally:
            sink.terminate()
            sink.wait(10)
    return ways


def _wait_for(port: int) -> None:
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"the sink server on port {port} did not start")


def report(ways: list[Way]) -> str:
    """The table of ``ways`` (whole, then in pieces) and their ratios."""
    rows = [
        f"{w.name:<10} {w.uploads:>7}  {w.answered:>8}  {w.cpu_s:>12.1f}  "
        f"{w.last_head_s:>17.2f}  {w.wall_s:>6.1f}"
        for w in ways
    ]
    whole, pieces = ways
    cpu = whole.cpu_s / max(pieces.cpu_s, 1e-9)
    head = whole.last_head_s / max(pieces.last_head_s, 1e-3)
    wall = whole.wall_s / max(pieces.wall_s, 1e-9)
    ratios = f"whole / in pieces: client CPU {cpu:.1f}×, last head {head:.0f}×, wall {wall:.1f}×"
    header = "way        uploads  answered  client CPU s  last head after s  wall s"
    return "\n".join([header, *rows, ratios])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uploads", type=int, default=50)
    parser.add_argument("--mib", type=float, default=48.0, help="each body's size")
    parser.add_argument("--hold", type=float, default=2.0, help="seconds before the answer")
    parser.add_argument("--serve", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--heads", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve is not None:
        asyncio.run(_sink(args.serve, args.hold, args.heads))
        return
    print(report(measure(args.uploads, args.mib, args.hold)))


if __name__ == "__main__":
    main()
