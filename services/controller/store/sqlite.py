"""The SQLite back end: one file (or memory) database, one connection shared between threads
under a lock, in WAL mode with its log checkpointed off the caller's thread
(:class:`~services.controller.checkpoint.Checkpointer`, never inside a commit).

One controller per file: SQLite has no leases, the controller that opens it runs every search in
it. Deleted pages are reused by later writes; the file does not shrink (no ``VACUUM``, which
would rewrite the whole database under the lock).
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from services.controller.checkpoint import Checkpointer
from services.controller.store.database import DatabaseUnavailable, Dialect, Rows, Session
from services.controller.store.migrations import migrate

__all__ = ["SqliteDatabase", "database_path"]


def database_path(url: str) -> str:
    """The SQLite file of a ``sqlite:///path`` URL (``sqlite:///:memory:`` for none)."""
    prefix = "sqlite:///"
    if not url.startswith(prefix):
        raise ValueError(
            "COSMOS_CONTROLLER_DATABASE_URL must look like sqlite:///path/to/file.db or "
            f"postgresql://user:password@host:port/database, got {url!r}"
        )
    path = url[len(prefix) :]
    if not path:
        raise ValueError("COSMOS_CONTROLLER_DATABASE_URL names no file")
    if path != ":memory:":
        Path(path).expanduser().parent.mkdir(parents=True, exist_ok=True)
    return path


class _Locked:
    """The shared connection, as a session (its statements run under the caller's lock)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def execute(self, sql: str, args: Sequence[Any] = ()) -> Rows:
        return self._db.execute(sql, tuple(args))


class SqliteDatabase:
    """A SQLite database (``sqlite:///path``), migrated on opening; safe to share between
    threads. A file database's log is checkpointed every ``checkpoint_every_s`` seconds."""

    dialect: Dialect = "sqlite"

    def __init__(self, url: str, *, checkpoint_every_s: float = 1.0) -> None:
        self.path = database_path(url)
        self.connection = sqlite3.connect(
            self.path, check_same_thread=False, isolation_level=None, timeout=10.0
        )
        self._lock = threading.Lock()
        self._closed = False
        db = self.connection
        wal = db.execute("PRAGMA journal_mode=WAL").fetchone()[0] == "wal"
        db.execute("PRAGMA synchronous=NORMAL")
        db.execute("PRAGMA foreign_keys=ON")
        if wal:  # no commit on the event loop copies the log back: the Checkpointer does
            db.execute("PRAGMA wal_autocheckpoint=0")
        with self.write() as session:
            migrate(self, session)
        self.checkpointer = Checkpointer(self.path, checkpoint_every_s) if wal else None

    @contextmanager
    def read(self) -> Iterator[Session]:
        with self._lock:
            yield _Locked(self.connection)

    @contextmanager
    def write(self) -> Iterator[Session]:
        with self._lock:
            self.connection.execute("BEGIN")
            try:
                yield _Locked(self.connection)
            except BaseException:
                self.connection.execute("ROLLBACK")
                raise
            self.connection.execute("COMMIT")

    def stamp(self, when: datetime) -> str:
        """ISO 8601 with ``+00:00``, which sorts as the times do."""
        return when.astimezone(UTC).isoformat()

    def when(self, stored: Any) -> datetime:
        return datetime.fromisoformat(stored)

    def database_bytes(self) -> int:
        with self.read() as session:
            pages = session.execute("PRAGMA page_count").fetchone()[0]
            free = session.execute("PRAGMA freelist_count").fetchone()[0]
            page_size = session.execute("PRAGMA page_size").fetchone()[0]
        return int((pages - free) * page_size)

    def ping(self) -> None:
        try:
            with self.read() as session:
                session.execute("SELECT 1 FROM searches LIMIT 1").fetchone()
        except sqlite3.Error as exc:
            raise DatabaseUnavailable(f"the SQLite database {self.path} fails: {exc}") from exc

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.checkpointer is not None:
            self.checkpointer.close()
        with self._lock:
            self.connection.close()
