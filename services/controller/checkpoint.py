"""Checkpoints of the store's write-ahead log, on a thread of their own.

SQLite in WAL mode copies the log back into the database file (a *checkpoint*) inside whichever
commit first finds the log over 1000 pages. With ~230 KB target images that is every ~17
searches, and that one commit then takes ~40 ms instead of ~1 ms (measured on the 2-core bench
machine) on the controller's event loop, stalling every search in flight. The store turns the
automatic checkpoint off and this thread runs a ``PASSIVE`` one every ``every_s`` seconds from a
connection of its own: it neither waits for nor blocks the loop's readers and writers, and the
sqlite3 module releases the GIL while it copies.
"""

from __future__ import annotations

import logging
import sqlite3
import threading

__all__ = ["Checkpointer"]

_log = logging.getLogger("cosmos.controller")


class Checkpointer:
    """Checkpoints the database at ``path`` every ``every_s`` seconds until :meth:`close`."""

    def __init__(self, path: str, every_s: float = 1.0) -> None:
        if every_s <= 0:
            raise ValueError("every_s must be positive")
        self.path = path
        self.every_s = every_s
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self.runs = 0
        """Checkpoints run by the thread so far."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sqlite-checkpoint", daemon=True)
        self._thread.start()

    def checkpoint(self, mode: str = "PASSIVE") -> tuple[int, int, int]:
        """One checkpoint now: (busy, frames in the log, frames copied), as SQLite reports."""
        if mode not in ("PASSIVE", "TRUNCATE"):
            raise ValueError(f"unknown checkpoint mode {mode!r}")
        busy, log, copied = self._db.execute(f"PRAGMA wal_checkpoint({mode})").fetchone()
        return int(busy), int(log), int(copied)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                self.checkpoint()
                self.runs += 1
            except sqlite3.Error as exc:  # a busy or closing database: try again next time
                _log.warning("checkpoint of %s failed: %s", self.path, exc)

    def close(self) -> None:
        """Stop the thread, then copy and empty the log (the loop's connection is still open)."""
        self._stop.set()
        self._thread.join()
        try:
            self.checkpoint("TRUNCATE")
        except sqlite3.Error as exc:
            _log.warning("final checkpoint of %s failed: %s", self.path, exc)
        self._db.close()
