"""A TCP relay that delays what it forwards: a link's latency where the kernel has no netem.

This machine's kernel has no ``sch_netem`` (``tc qdisc add ... netem`` answers "Specified qdisc
kind is unknown"), and none of the qdiscs it has (tbf, htb, pfifo) holds a packet back for a
time: they only shape a rate. So :mod:`tests.hosts.network` puts this relay in front of a
service on a host placed ``impairable``, inside that host: it listens on the host's address and
the service's port, and forwards each connection to the service on an inner port of the same
address. Loss stays the kernel's (the network's htb and BPF filter drop real packets, and TCP
retransmits); where the kernel has netem, the network uses netem for both and no relay runs.

Each chunk read from one side is written to the other ``d`` after it was read (``d``: the
one-way delay), in order, in each direction, so a request and its answer gain ``2 d`` as over a
link with ``d`` each way. At most 64 chunks wait per direction (the reader then waits too). A
half-closed side is half-closed on the other once its chunks are delivered.

``python -m tests.hosts.relay ADDRESS:PORT UPSTREAM_PORT``: prints ``ready`` once listening, then
reads commands on stdin, ``delay <ms>``, answering ``ok`` to each, until stdin closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import threading

__all__ = ["Relay", "main"]

WAITING_CHUNKS = 64
CHUNK_BYTES = 65536


class Relay:
    """Connections to ``listen`` forwarded to ``upstream``, delayed by :attr:`delay_s`."""

    def __init__(self, listen: tuple[str, int], upstream: tuple[str, int]) -> None:
        self.listen = listen
        self.upstream = upstream
        self.delay_s = 0.0

    async def serve(self) -> asyncio.Server:
        host, port = self.listen
        return await asyncio.start_server(self._connection, host, port, reuse_address=True)

    async def _connection(
        self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter
    ) -> None:
        try:
            upstream_reader, upstream_writer = await asyncio.open_connection(*self.upstream)
        except OSError:
            client_writer.close()
            return
        writers = (client_writer, upstream_writer)
        try:
            async with asyncio.TaskGroup() as pumps:  # one failing cancels the other
                pumps.create_task(self._pump(client_reader, upstream_writer))
                pumps.create_task(self._pump(upstream_reader, client_writer))
        except* OSError:
            pass  # a side went away: so does the other
        finally:
            for writer in writers:
                writer.close()
            for writer in writers:
                with contextlib.suppress(OSError):
                    await writer.wait_closed()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Copy ``reader`` to ``writer``, each chunk ``delay_s`` after it was read."""
        loop = asyncio.get_running_loop()
        waiting: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue(WAITING_CHUNKS)

        async def deliver() -> None:
            while True:
                due, chunk = await waiting.get()
                late = due - loop.time()
                if late > 0:
                    await asyncio.sleep(late)
                if not chunk:
                    if writer.can_write_eof():
                        writer.write_eof()
                    return
                writer.write(chunk)
                await writer.drain()

        delivering = asyncio.create_task(deliver())
        try:
            while True:
                chunk = await reader.read(CHUNK_BYTES)
                await waiting.put((loop.time() + self.delay_s, chunk))
                if not chunk:
                    break
            await delivering
        finally:
            delivering.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await delivering


def _commands(loop: asyncio.AbstractEventLoop, relay: Relay, done: asyncio.Event) -> None:
    """Read ``delay <ms>`` lines from stdin (on a thread) until it closes."""
    for line in sys.stdin:
        words = line.split()
        if len(words) == 2 and words[0] == "delay":
            delay_s = max(0.0, float(words[1]) / 1000.0)
            applied = threading.Event()

            def apply(value: float = delay_s, applied: threading.Event = applied) -> None:
                relay.delay_s = value
                applied.set()

            loop.call_soon_threadsafe(apply)
            applied.wait()
            print("ok", flush=True)  # noqa: T201 (the relay's answer on its control pipe)
        else:
            print(f"unknown command {line.strip()!r}", flush=True)  # noqa: T201
    loop.call_soon_threadsafe(done.set)


async def _main(listen: tuple[str, int], upstream: tuple[str, int]) -> None:
    relay = Relay(listen, upstream)
    server = await relay.serve()
    done = asyncio.Event()
    loop = asyncio.get_running_loop()
    threading.Thread(target=_commands, args=(loop, relay, done), daemon=True).start()
    print("ready", flush=True)  # noqa: T201
    async with server:
        await done.wait()


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        raise SystemExit("usage: python -m tests.hosts.relay ADDRESS:PORT UPSTREAM_PORT")
    address, _, port = args[0].rpartition(":")
    asyncio.run(_main((address, int(port)), (address, int(args[1]))))


if __name__ == "__main__":
    main()
