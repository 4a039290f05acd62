"""Change notifications between controllers that share PostgreSQL: every write of a search
announces its id on a channel (``pg_notify`` in the write's transaction, so it is delivered on
commit, and never for a write rolled back), and each controller listens on a connection of its
own, on a thread, and wakes the followers of that search (its event streams).

A notification sent while a listener is disconnected is lost (PostgreSQL keeps none for
absent listeners), so a listener that (re)connects reports that with ``None``: its controller
wakes every follower, which reads the store again.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import psycopg

from services.controller.store.database import Session

__all__ = ["CHANNEL", "ChangeListener", "announce"]

CHANNEL = "cosmos_search_changed"

_log = logging.getLogger("cosmos.controller")


def announce(session: Session, search_id: str) -> None:
    """Tell every listening controller that ``search_id`` changed, once the transaction of
    ``session`` commits."""
    session.execute("SELECT pg_notify(?, ?)", (CHANNEL, search_id))


class ChangeListener:
    """Calls ``on_change(search_id)`` for each change announced on the database at ``url``
    (``on_change(None)``: connected, changes may have been missed), from a thread of its own,
    until :meth:`close`; reconnects every ``retry_s`` while the database is away."""

    def __init__(
        self, url: str, on_change: Callable[[str | None], None], *, retry_s: float = 1.0
    ) -> None:
        self._url = url
        self._on_change = on_change
        self._retry_s = retry_s
        self._stop = threading.Event()
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pg-listen", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                with psycopg.connect(self._url, autocommit=True, connect_timeout=5) as db:
                    db.execute(f"LISTEN {CHANNEL}")
                    self.connected.set()
                    self._on_change(None)
                    while not self._stop.is_set():
                        for note in db.notifies(timeout=0.5):
                            self._on_change(note.payload)
            except psycopg.Error as exc:
                if not self._stop.is_set():
                    _log.warning("listening for search changes failed: %s", exc)
            self.connected.clear()
            self._stop.wait(self._retry_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
