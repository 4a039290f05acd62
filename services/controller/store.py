"""Persistence of searches in SQLite: the search, its target image, its iterations, its result.

One row per search (its JSON document and the fields queries need), one per target image and one
per iteration. The image has a table of its own: SQLite rewrites a whole row on every update, and a
search's document changes several times per search while its ~230 KB image never does (measured:
0.39 ms per update with the image in the row, 0.04 ms without). Writes are committed as they
happen, so a controller that dies loses nothing recorded: queued and running searches are found
again by :meth:`SearchStore.unfinished`. The write-ahead log is copied back into the database by a
:class:`~services.controller.checkpoint.Checkpointer` thread, never inside a commit.

Each search has an owner (the id of the API key that submitted it, or none when the controller
ran without keys); queries take ``visible_to``, the key id whose searches alone are seen (None:
everyone's). What a search holds is bounded: a failed search's target image is deleted when it
fails (the record stays, to say why), and :meth:`SearchStore.expire` deletes finished searches
with their images and iterations (as :meth:`SearchStore.delete_finished` does one, when its
tenant asks). Deleted pages are reused by later writes; the file does not shrink (no
``VACUUM``, which would rewrite the whole database under the lock). A cancelled search stays
cancelled, whatever its stopping run writes after the cancel (:meth:`SearchStore.update`).
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypedDict, Unpack

from services.common.contracts.detect import Detection, ModelInfo
from services.common.contracts.search import (
    OUTAGE,
    TERMINAL_STATUSES,
    Iteration,
    Search,
    SearchResult,
    SearchStatus,
)
from services.common.errors import ProblemDetails
from services.controller.checkpoint import Checkpointer

__all__ = ["SearchStore", "StoreSize", "Usage", "database_path", "utcnow"]

_TABLES = """
CREATE TABLE IF NOT EXISTS searches (
    id TEXT PRIMARY KEY,
    status TEXT NOT NULL,
    created_at TEXT NOT NULL,
    doc TEXT NOT NULL,
    owner TEXT,
    finished_at TEXT,
    image_bytes INTEGER NOT NULL DEFAULT 0
);
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

_ADDED_COLUMNS = {
    "owner": "TEXT",
    "finished_at": "TEXT",
    "image_bytes": "INTEGER NOT NULL DEFAULT 0",
}
"""Columns a database from an earlier version lacks: added, then filled in, on opening."""

# After the columns: an earlier version's table gets them before they are indexed.
_INDEXES = """
CREATE INDEX IF NOT EXISTS searches_created ON searches (created_at DESC);
CREATE INDEX IF NOT EXISTS searches_owner_created ON searches (owner, created_at);
CREATE INDEX IF NOT EXISTS searches_owner_status ON searches (owner, status, image_bytes);
CREATE INDEX IF NOT EXISTS searches_finished ON searches (finished_at)
    WHERE finished_at IS NOT NULL;
"""

_VISIBLE = "(?1 IS NULL OR owner = ?1)"
"""The condition of ``visible_to`` (parameter 1): everyone's searches, or one owner's."""


@dataclass(frozen=True)
class Usage:
    """What one owner holds, for its quotas."""

    active: int
    """Searches queued or running."""
    recent: int
    """Searches created since the time asked about."""
    first_recent: datetime | None
    """When the oldest of those was created."""
    image_bytes: int
    """Bytes of the target images its searches hold."""
    first_expiry: datetime | None
    """When the first of its finished searches that hold an image finished."""


@dataclass(frozen=True)
class StoreSize:
    """How much the store holds (the controller's ``/health``)."""

    searches: int
    image_bytes: int
    """Bytes of the target images held."""
    database_bytes: int
    """Bytes of the database's pages in use (free pages, and the write-ahead log, aside)."""


class SearchChanges(TypedDict, total=False):
    """What :meth:`SearchStore.update` may change (None: leave as it is)."""

    status: SearchStatus | None
    result: SearchResult | None
    error: ProblemDetails | None
    target_detections: tuple[Detection, ...] | None
    target_model: ModelInfo | None


def utcnow() -> datetime:
    return datetime.now(UTC)


def _stamp(when: datetime) -> str:
    """A UTC time as stored: ISO 8601 with ``+00:00``, which sorts as the times do."""
    return when.astimezone(UTC).isoformat()


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
            self._db.executescript(_TABLES)
            if wal:  # no commit on the event loop copies the log back: the Checkpointer does
                self._db.execute("PRAGMA wal_autocheckpoint=0")
        self._checkpointer = Checkpointer(path, checkpoint_every_s) if wal else None
        self._move_images()
        self._add_columns()
        with self._lock:
            self._db.executescript(_INDEXES)

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

    def _add_columns(self) -> None:
        """Give a database from an earlier version the owner, finish time and image size of each
        search; its searches have no owner (only admin keys see them), its finished ones finished
        when last updated, its failed ones lose their images as they would have on failing."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(searches)")}
        missing = [name for name in _ADDED_COLUMNS if name not in columns]
        if not missing:
            return
        with self._transaction():
            for name in missing:
                self._db.execute(f"ALTER TABLE searches ADD COLUMN {name} {_ADDED_COLUMNS[name]}")
            finished = self._db.execute(
                "SELECT id, doc FROM searches WHERE status IN ('succeeded', 'failed', 'cancelled')"
            ).fetchall()
            for search_id, doc in finished:
                updated = Search.model_validate_json(doc).updated_at
                self._db.execute(
                    "UPDATE searches SET finished_at = ? WHERE id = ?", (_stamp(updated), search_id)
                )
            self._db.execute(
                "DELETE FROM images WHERE search_id IN "
                "(SELECT id FROM searches WHERE status = 'failed')"
            )
            self._db.execute(
                "UPDATE searches SET image_bytes = coalesce("
                "(SELECT length(image) FROM images WHERE search_id = searches.id), 0)"
            )

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

    def create(self, search: Search, image: bytes, *, owner: str | None = None) -> None:
        """Record a new search and its target image; ``owner`` is the submitting key's id."""
        doc = search.model_copy(update={"iterations": ()}).model_dump_json()
        with self._transaction():
            self._db.execute(
                "INSERT INTO searches (id, status, created_at, doc, owner, image_bytes) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (search.id, search.status, _stamp(search.created_at), doc, owner, len(image)),
            )
            self._db.execute(
                "INSERT INTO images (search_id, image) VALUES (?, ?)", (search.id, image)
            )

    def discard(self, search_id: str) -> bool:
        """Delete a search with its image and iterations, as if never recorded (a submission
        cancelled while it was being stored); whether it was there."""
        with self._transaction():
            cursor = self._db.execute("DELETE FROM searches WHERE id = ?", (search_id,))
        return cursor.rowcount > 0

    def delete_finished(self, search_id: str) -> tuple[str | None, datetime] | None:
        """Delete a finished (succeeded, failed or cancelled) search with its image and
        iterations: its owner and creation time, or None when no such search is held."""
        with self._transaction():
            rows = self._db.execute(
                "DELETE FROM searches WHERE id = ? AND status IN "
                "('succeeded', 'failed', 'cancelled') RETURNING owner, created_at",
                (search_id,),
            ).fetchall()
        return (rows[0][0], datetime.fromisoformat(rows[0][1])) if rows else None

    def get(self, search_id: str, *, visible_to: str | None = None) -> Search | None:
        """The search with its iterations, or None (also when ``visible_to`` does not own it)."""
        row = self._one(
            f"SELECT doc FROM searches WHERE id = ?2 AND {_VISIBLE}", visible_to, search_id
        )
        if row is None:
            return None
        search = Search.model_validate_json(row[0])
        return search.model_copy(update={"iterations": tuple(self.iterations(search_id))})

    def holds_image(self, search_id: str) -> bool:
        """Whether the search's target image is still held."""
        return self._one("SELECT 1 FROM images WHERE search_id = ?", search_id) is not None

    def image(self, search_id: str) -> bytes:
        row = self._one("SELECT image FROM images WHERE search_id = ?", search_id)
        if row is None:
            raise KeyError(search_id)
        return bytes(row[0])

    def page(
        self, limit: int, offset: int, *, visible_to: str | None = None
    ) -> tuple[list[Search], int]:
        """Newest first, without iterations (they can be long), and the total count."""
        with self._lock:
            rows = self._db.execute(
                f"SELECT doc FROM searches WHERE {_VISIBLE} "
                "ORDER BY created_at DESC, id LIMIT ?2 OFFSET ?3",
                (visible_to, limit, offset),
            ).fetchall()
            total = self._db.execute(
                f"SELECT COUNT(*) FROM searches WHERE {_VISIBLE}", (visible_to,)
            ).fetchone()[0]
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

    def status_doc(
        self, search_id: str, *, visible_to: str | None = None
    ) -> tuple[SearchStatus, str] | None:
        """The search's status and its JSON document without iterations, or None (also when
        ``visible_to`` does not own it)."""
        row = self._one(
            f"SELECT status, doc FROM searches WHERE id = ?2 AND {_VISIBLE}", visible_to, search_id
        )
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
        """Change a search's status, result, error or target detections; stamps ``updated_at``,
        and a search's finish time when it finishes. A search that fails loses its target image
        (nothing reads it again; its record says why it failed), unless it failed for an outage
        (:data:`OUTAGE`): it may be retried.

        A cancelled search stays cancelled: its status, result and error are not changed again
        (a run winding down after the cancel writes what it did, never over the cancel)."""
        with self._lock:
            return self._update(search_id, changes)

    def _update(self, search_id: str, changes: SearchChanges) -> Search:
        """:meth:`update`, with the lock held."""
        row = self._db.execute(
            "SELECT doc, status FROM searches WHERE id = ?", (search_id,)
        ).fetchone()
        if row is None:
            raise KeyError(search_id)
        given = {key: value for key, value in changes.items() if value is not None}
        if row[1] == "cancelled":
            given = {k: v for k, v in given.items() if k not in {"status", "result", "error"}}
        search = Search.model_validate_json(row[0]).model_copy(
            update={**given, "updated_at": utcnow()}
        )
        finishes = search.status in TERMINAL_STATUSES
        self._db.execute(
            "UPDATE searches SET status = ?, doc = ?, "
            "finished_at = CASE WHEN ? THEN coalesce(finished_at, ?) END WHERE id = ?",
            (
                search.status,
                search.model_dump_json(),
                finishes,
                _stamp(search.updated_at),
                search_id,
            ),
        )
        if search.status == "failed" and (search.error is None or search.error.type != OUTAGE):
            self._db.execute("DELETE FROM images WHERE search_id = ?", (search_id,))
            self._db.execute("UPDATE searches SET image_bytes = 0 WHERE id = ?", (search_id,))
        return search

    def reopen(self, search_id: str) -> Search:
        """Queue a finished search again: status ``queued``, its error and finish time dropped
        (it resumes from its recorded iterations); stamps ``updated_at``."""
        with self._lock:
            row = self._db.execute("SELECT doc FROM searches WHERE id = ?", (search_id,)).fetchone()
            if row is None:
                raise KeyError(search_id)
            search = Search.model_validate_json(row[0]).model_copy(
                update={"status": "queued", "error": None, "updated_at": utcnow()}
            )
            self._db.execute(
                "UPDATE searches SET status = ?, doc = ?, finished_at = NULL WHERE id = ?",
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

    def usage(self, owner: str, since: datetime) -> Usage:
        """What ``owner``'s searches hold, and how many it created since ``since``."""
        with self._lock:
            active, image_bytes = self._db.execute(
                "SELECT count(CASE WHEN status IN ('queued', 'running') THEN 1 END), "
                "coalesce(sum(image_bytes), 0) FROM searches WHERE owner = ?",
                (owner,),
            ).fetchone()
            recent, first_recent = self._db.execute(
                "SELECT count(*), min(created_at) FROM searches "
                "WHERE owner = ? AND created_at >= ?",
                (owner, _stamp(since)),
            ).fetchone()
            (first_expiry,) = self._db.execute(
                "SELECT min(finished_at) FROM searches "
                "WHERE owner = ? AND finished_at IS NOT NULL AND image_bytes > 0",
                (owner,),
            ).fetchone()
        return Usage(
            active=int(active),
            recent=int(recent),
            first_recent=None if first_recent is None else datetime.fromisoformat(first_recent),
            image_bytes=int(image_bytes),
            first_expiry=None if first_expiry is None else datetime.fromisoformat(first_expiry),
        )

    def expire(self, finished_before: datetime, batch: int = 200) -> int:
        """Delete the searches that finished before ``finished_before``, with their images and
        iterations; how many. In batches of ``batch``, each its own transaction, so that other
        requests get the lock between them."""
        expired = 0
        while True:
            with self._transaction():
                deleted = self._db.execute(
                    "DELETE FROM searches WHERE id IN (SELECT id FROM searches "
                    "WHERE finished_at IS NOT NULL AND finished_at < ? LIMIT ?)",
                    (_stamp(finished_before), batch),
                ).rowcount
            expired += deleted
            if deleted < batch:
                return expired

    def size(self) -> StoreSize:
        """How many searches the store holds, their images' bytes, the database's bytes."""
        with self._lock:
            searches, image_bytes = self._db.execute(
                "SELECT count(*), coalesce(sum(image_bytes), 0) FROM searches"
            ).fetchone()
            pages = self._db.execute("PRAGMA page_count").fetchone()[0]
            free = self._db.execute("PRAGMA freelist_count").fetchone()[0]
            page_size = self._db.execute("PRAGMA page_size").fetchone()[0]
        return StoreSize(
            searches=int(searches),
            image_bytes=int(image_bytes),
            database_bytes=int((pages - free) * page_size),
        )
