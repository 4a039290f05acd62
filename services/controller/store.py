"""Persistence of searches in SQLite: the search, its target image, its iterations, its result.

One row per search (its JSON document and the fields queries need), one per target image and one
per iteration. The image has a table of its own: SQLite rewrites a whole row on every update, and a
search's document changes several times per search while its ~230 KB image never does (measured:
0.39 ms per update with the image in the row, 0.04 ms without). Writes are committed as they
happen, so a controller that dies loses nothing recorded: queued and running searches are found
again by :meth:`SearchStore.unfinished`. The write-ahead log is copied back into the database by a
:class:`~services.controller.checkpoint.Checkpointer` thread, never inside a commit.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypedDict, Unpack

from services.common.contracts.detect import Detection, ModelInfo
from services.common.contracts.search import Iteration, Search, SearchResult, SearchStatus
from services.common.errors import ProblemDetails
from services.controller.checkpoint import Checkpointer

__all__ = ["SearchStore", "database_path", "utcnow"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS searches (
    id TEXT PRIMARY KEY,
    status TEXT NOT NULL,
    created_at TEXT NOT NULL,
    doc TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS searches_created ON searches (created_at DESC);
CREATE TABLE IF NOT EXISTS images (
    search_id TEXT PRIMARY KEY REFERENCES searches (id) ON DELETE CASCADE,
    image BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS iterations (
    search_id TEXT NOT NULL REFERENCES searches (id) ON DELETE CASCADE,
    idx INTEGER NOT NULL,
    doc TEXT NOT NULL,
    PRIMARY KEY (search_id, idx)
);
"""


class SearchChanges(TypedDict, total=False):
    """What :meth:`SearchStore.update` may change (None: leave as it is)."""

    status: SearchStatus | None
    result: SearchResult | None
    error: ProblemDetails | None
    target_detections: tuple[Detection, ...] | None
    target_model: ModelInfo | None


def utcnow() -> datetime:
    return datetime.now(UTC)


def database_path(url: str) -> str:
    """The SQLite file of a ``sqlite:///path`` URL (``sqlite:///:memory:`` for none)."""
    prefix = "sqlite:///"
    if not url.startswith(prefix):
        raise ValueError(
            f"COSMOS_CONTROLLER_DATABASE_URL must look like sqlite:///path/to/file.db, got {url!r}"
        )
    path = url[len(prefix) :]
    if not path:
        raise ValueError("COSMOS_CONTROLLER_DATABASE_URL names no file")
    if path != ":memory:":
        Path(path).expanduser().parent.mkdir(parents=True, exist_ok=True)
    return path


class SearchStore:
    """Searches in one SQLite database; safe to share between threads. A file database's log is
    checkpointed every ``checkpoint_every_s`` seconds off the caller's thread."""

    def __init__(self, url: str, *, checkpoint_every_s: float = 1.0) -> None:
        path = database_path(url)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        with self._lock:
            wal = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0] == "wal"
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_SCHEMA)
            if wal:  # no commit on the event loop copies the log back: the Checkpointer does
                self._db.execute("PRAGMA wal_autocheckpoint=0")
        self._checkpointer = Checkpointer(path, checkpoint_every_s) if wal else None
        self._move_images()

    def _move_images(self) -> None:
        """Move target images out of the search rows of a database from an earlier version."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(searches)")}
        if "image" not in columns:
            return
        with self._transaction():
            self._db.execute(
                "INSERT OR IGNORE INTO images (search_id, image) SELECT id, image FROM searches"
            )
            self._db.execute("ALTER TABLE searches DROP COLUMN image")

    def close(self) -> None:
        if self._checkpointer is not None:
            self._checkpointer.close()
        with self._lock:
            self._db.close()

    @contextmanager
    def _transaction(self) -> Iterator[None]:
        """The lock and one transaction: committed at the end of the block, or rolled back."""
        with self._lock:
            self._db.execute("BEGIN")
            try:
                yield
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _one(self, sql: str, *args: Any) -> Any:
        with self._lock:
            return self._db.execute(sql, args).fetchone()

    def create(self, search: Search, image: bytes) -> None:
        """Record a new search and its target image."""
        doc = search.model_copy(update={"iterations": ()}).model_dump_json()
        with self._transaction():
            self._db.execute(
                "INSERT INTO searches (id, status, created_at, doc) VALUES (?, ?, ?, ?)",
                (search.id, search.status, search.created_at.isoformat(), doc),
            )
            self._db.execute(
                "INSERT INTO images (search_id, image) VALUES (?, ?)", (search.id, image)
            )

    def get(self, search_id: str) -> Search | None:
        """The search with its iterations, or None."""
        row = self._one("SELECT doc FROM searches WHERE id = ?", search_id)
        if row is None:
            return None
        search = Search.model_validate_json(row[0])
        return search.model_copy(update={"iterations": tuple(self.iterations(search_id))})

    def image(self, search_id: str) -> bytes:
        row = self._one("SELECT image FROM images WHERE search_id = ?", search_id)
        if row is None:
            raise KeyError(search_id)
        return bytes(row[0])

    def page(self, limit: int, offset: int) -> tuple[list[Search], int]:
        """Newest first, without iterations (they can be long), and the total count."""
        with self._lock:
            rows = self._db.execute(
                "SELECT doc FROM searches ORDER BY created_at DESC, id LIMIT ? OFFSET ?",
                (limit, offset),
            ).fetchall()
            total = self._db.execute("SELECT COUNT(*) FROM searches").fetchone()[0]
        return [Search.model_validate_json(row[0]) for row in rows], int(total)

    def iterations(self, search_id: str) -> list[Iteration]:
        return [Iteration.model_validate_json(doc) for doc in self.iteration_docs(search_id)]

    def iteration_docs(self, search_id: str, start: int = 0) -> list[str]:
        """The recorded iterations from index ``start`` on, as their JSON documents."""
        with self._lock:
            rows = self._db.execute(
                "SELECT doc FROM iterations WHERE search_id = ? AND idx >= ? ORDER BY idx",
                (search_id, start),
            ).fetchall()
        return [row[0] for row in rows]

    def status_doc(self, search_id: str) -> tuple[SearchStatus, str] | None:
        """The search's status and its JSON document without iterations, or None."""
        row = self._one("SELECT status, doc FROM searches WHERE id = ?", search_id)
        return None if row is None else (row[0], row[1])

    def add_iteration(
        self,
        search_id: str,
        iteration: Iteration,
        **changes: Unpack[SearchChanges],
    ) -> None:
        """Record an iteration (replacing one of the same index, as a resumed search may) and
        ``changes`` of the search (the target's detections, the final status and result) in one
        transaction."""
        with self._transaction():
            self._db.execute(
                "INSERT OR REPLACE INTO iterations (search_id, idx, doc) VALUES (?, ?, ?)",
                (search_id, iteration.index, iteration.model_dump_json()),
            )
            self._update(search_id, changes)

    def update(self, search_id: str, **changes: Unpack[SearchChanges]) -> Search:
        """Change a search's status, result, error or target detections; stamps ``updated_at``."""
        with self._lock:
            return self._update(search_id, changes)

    def _update(self, search_id: str, changes: SearchChanges) -> Search:
        """:meth:`update`, with the lock held."""
        row = self._db.execute("SELECT doc FROM searches WHERE id = ?", (search_id,)).fetchone()
        if row is None:
            raise KeyError(search_id)
        given = {key: value for key, value in changes.items() if value is not None}
        search = Search.model_validate_json(row[0]).model_copy(
            update={**given, "updated_at": utcnow()}
        )
        self._db.execute(
            "UPDATE searches SET status = ?, doc = ? WHERE id = ?",
            (search.status, search.model_dump_json(), search_id),
        )
        return search

    def reopen(self, search_id: str) -> Search:
        """Queue a finished search again: status ``queued``, its error dropped (it resumes from
        its recorded iterations); stamps ``updated_at``."""
        with self._lock:
            row = self._db.execute("SELECT doc FROM searches WHERE id = ?", (search_id,)).fetchone()
            if row is None:
                raise KeyError(search_id)
            search = Search.model_validate_json(row[0]).model_copy(
                update={"status": "queued", "error": None, "updated_at": utcnow()}
            )
            self._db.execute(
                "UPDATE searches SET status = ?, doc = ? WHERE id = ?",
                (search.status, search.model_dump_json(), search_id),
            )
        return search

    def unfinished(self) -> list[str]:
        """Ids of queued and running searches, oldest first (to resume after a restart)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id FROM searches WHERE status IN ('queued', 'running') "
                "ORDER BY created_at, id"
            ).fetchall()
        return [row[0] for row in rows]
