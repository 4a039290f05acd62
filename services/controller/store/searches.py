"""Persistence of searches: the search, its target image, its iterations, its result, in either
back end (:mod:`.sqlite`, :mod:`.postgres`).

One row per search (its JSON document and the fields queries need), one per target image and one
per iteration. The image has a table of its own: SQLite rewrites a whole row on every update, and a
search's document changes several times per search while its ~230 KB image never does (measured:
0.39 ms per update with the image in the row, 0.04 ms without). Writes are committed as they
happen, so a controller that dies loses nothing recorded: queued and running searches are found
again by :meth:`SearchStore.unfinished` (or, on PostgreSQL, claimed by :mod:`.leases`).

Each search has an owner (the id of the API key that submitted it, or none when the controller
ran without keys); queries take ``visible_to``, the key id whose searches alone are seen (None:
everyone's). What a search holds is bounded: a failed search's target image is deleted when it
fails (the record stays, to say why), and :meth:`SearchStore.expire` deletes finished searches
with their images and iterations (as :meth:`SearchStore.delete_finished` does one, when its
tenant asks). A cancelled search stays cancelled, whatever its stopping run writes after the
cancel (:meth:`SearchStore.update`).

A run's writes may carry its :class:`~.leases.Lease`: they are then refused
(:class:`~.leases.LeaseLost`) unless that lease is still the search's newest, in the same
transaction (fencing: a controller that lost a search to another never writes to it again).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
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
from services.controller.store.changes import announce
from services.controller.store.database import Database, Session
from services.controller.store.leases import Lease, Leases, fence

__all__ = ["SearchChanges", "SearchStore", "StoreSize", "Usage", "utcnow"]

_VISIBLE = "(CAST(? AS TEXT) IS NULL OR owner = ?)"
"""The condition of ``visible_to`` (given twice): everyone's searches, or one owner's."""

_FINISHED = "('succeeded', 'failed', 'cancelled')"
_UNFINISHED = "('queued', 'running')"


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
    """Bytes of the database in use (SQLite: its pages, free pages and the log aside)."""


class SearchChanges(TypedDict, total=False):
    """What :meth:`SearchStore.update` may change (None: leave as it is)."""

    status: SearchStatus | None
    result: SearchResult | None
    error: ProblemDetails | None
    target_detections: tuple[Detection, ...] | None
    target_model: ModelInfo | None


def utcnow() -> datetime:
    return datetime.now(UTC)


class SearchStore:
    """Searches in one database; safe to share between threads."""

    def __init__(self, database: Database) -> None:
        self.database = database

    def close(self) -> None:
        self.database.close()

    def _visible(self, visible_to: str | None) -> tuple[str | None, str | None]:
        return visible_to, visible_to

    def _changed(self, session: Session, search_id: str) -> None:
        """Announce the change to the other controllers (PostgreSQL: :mod:`.changes`)."""
        if self.database.dialect == "postgresql":
            announce(session, search_id)

    def create(
        self,
        search: Search,
        image: bytes,
        *,
        owner: str | None = None,
        leases: Leases | None = None,
    ) -> Lease | None:
        """Record a new search and its target image; ``owner`` is the submitting key's id. With
        ``leases`` (PostgreSQL), their controller takes the search's lease in the same
        transaction (:meth:`Leases.hold`), which is returned."""
        doc = search.model_copy(update={"iterations": ()}).model_dump_json()
        created = self.database.stamp(search.created_at)
        with self.database.write() as session:
            session.execute(
                "INSERT INTO searches (id, status, created_at, doc, owner, image_bytes) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (search.id, search.status, created, doc, owner, len(image)),
            )
            session.execute(
                "INSERT INTO images (search_id, image) VALUES (?, ?)", (search.id, image)
            )
            self._changed(session, search.id)
            return None if leases is None else leases.hold(session, search.id)

    def discard(self, search_id: str) -> bool:
        """Delete a search with its image and iterations, as if never recorded (a submission
        cancelled while it was being stored); whether it was there."""
        with self.database.write() as session:
            rows = session.execute("DELETE FROM searches WHERE id = ?", (search_id,))
            self._changed(session, search_id)
            return rows.rowcount > 0

    def delete_finished(self, search_id: str) -> tuple[str | None, datetime] | None:
        """Delete a finished (succeeded, failed or cancelled) search with its image and
        iterations: its owner and creation time, or None when no such search is held."""
        with self.database.write() as session:
            rows = session.execute(
                f"DELETE FROM searches WHERE id = ? AND status IN {_FINISHED} "
                "RETURNING owner, created_at",
                (search_id,),
            ).fetchall()
            self._changed(session, search_id)
        return (rows[0][0], self.database.when(rows[0][1])) if rows else None

    def get(self, search_id: str, *, visible_to: str | None = None) -> Search | None:
        """The search with its iterations, or None (also when ``visible_to`` does not own it)."""
        with self.database.read() as session:
            row = session.execute(
                f"SELECT doc FROM searches WHERE id = ? AND {_VISIBLE}",
                (search_id, *self._visible(visible_to)),
            ).fetchone()
            if row is None:
                return None
            docs = self._iteration_docs(session, search_id, 0)
        search = Search.model_validate_json(row[0])
        iterations = tuple(Iteration.model_validate_json(doc) for doc in docs)
        return search.model_copy(update={"iterations": iterations})

    def holds_image(self, search_id: str) -> bool:
        """Whether the search's target image is still held."""
        with self.database.read() as session:
            row = session.execute("SELECT 1 FROM images WHERE search_id = ?", (search_id,))
            return row.fetchone() is not None

    def image(self, search_id: str) -> bytes:
        with self.database.read() as session:
            row = session.execute(
                "SELECT image FROM images WHERE search_id = ?", (search_id,)
            ).fetchone()
        if row is None:
            raise KeyError(search_id)
        return bytes(row[0])

    def page(
        self, limit: int, offset: int, *, visible_to: str | None = None
    ) -> tuple[list[Search], int]:
        """Newest first, without iterations (they can be long), and the total count."""
        visible = self._visible(visible_to)
        with self.database.read() as session:
            rows = session.execute(
                f"SELECT doc FROM searches WHERE {_VISIBLE} "
                "ORDER BY created_at DESC, id LIMIT ? OFFSET ?",
                (*visible, limit, offset),
            ).fetchall()
            total = session.execute(
                f"SELECT COUNT(*) FROM searches WHERE {_VISIBLE}", visible
            ).fetchone()[0]
        return [Search.model_validate_json(row[0]) for row in rows], int(total)

    def iterations(self, search_id: str) -> list[Iteration]:
        return [Iteration.model_validate_json(doc) for doc in self.iteration_docs(search_id)]

    def iteration_docs(self, search_id: str, start: int = 0) -> list[str]:
        """The recorded iterations from index ``start`` on, as their JSON documents."""
        with self.database.read() as session:
            return self._iteration_docs(session, search_id, start)

    @staticmethod
    def _iteration_docs(session: Session, search_id: str, start: int) -> list[str]:
        rows = session.execute(
            "SELECT doc FROM iterations WHERE search_id = ? AND idx >= ? ORDER BY idx",
            (search_id, start),
        ).fetchall()
        return [row[0] for row in rows]

    def status_doc(
        self, search_id: str, *, visible_to: str | None = None
    ) -> tuple[SearchStatus, str] | None:
        """The search's status and its JSON document without iterations, or None (also when
        ``visible_to`` does not own it)."""
        with self.database.read() as session:
            row = session.execute(
                f"SELECT status, doc FROM searches WHERE id = ? AND {_VISIBLE}",
                (search_id, *self._visible(visible_to)),
            ).fetchone()
        return None if row is None else (row[0], row[1])

    def add_iteration(
        self,
        search_id: str,
        iteration: Iteration,
        lease: Lease | None = None,
        **changes: Unpack[SearchChanges],
    ) -> None:
        """Record an iteration (replacing one of the same index, as a resumed search may) and
        ``changes`` of the search (the target's detections, the final status and result) in one
        transaction; refused whole if ``lease`` is given and no longer the search's."""
        with self.database.write() as session:
            self._update(session, search_id, changes, lease)
            session.execute(
                "INSERT INTO iterations (search_id, idx, doc) VALUES (?, ?, ?) "
                "ON CONFLICT (search_id, idx) DO UPDATE SET doc = excluded.doc",
                (search_id, iteration.index, iteration.model_dump_json()),
            )

    def update(
        self, search_id: str, lease: Lease | None = None, **changes: Unpack[SearchChanges]
    ) -> Search:
        """Change a search's status, result, error or target detections; stamps ``updated_at``,
        and a search's finish time when it finishes. A search that fails loses its target image
        (nothing reads it again; its record says why it failed), unless it failed for an outage
        (:data:`OUTAGE`): it may be retried. Refused if ``lease`` is given and no longer the
        search's (:class:`~.leases.LeaseLost`).

        A cancelled search stays cancelled: its status, result and error are not changed again
        (a run winding down after the cancel writes what it did, never over the cancel). A
        cancel of a finished search changes nothing (one that arrives through another
        controller as the search succeeds leaves the success whole)."""
        with self.database.write() as session:
            return self._update(session, search_id, changes, lease)

    def _update(
        self, session: Session, search_id: str, changes: SearchChanges, lease: Lease | None
    ) -> Search:
        """:meth:`update`, in the transaction of ``session``. The search's row is locked
        before its lease is checked, the order in which a claim takes them (it skips a locked
        search), so a write and a claim never wait for each other in a cycle."""
        row = session.execute(
            "SELECT doc, status FROM searches WHERE id = ? FOR UPDATE"
            if self.database.dialect == "postgresql"
            else "SELECT doc, status FROM searches WHERE id = ?",
            (search_id,),
        ).fetchone()
        if row is None:
            raise KeyError(search_id)
        if lease is not None:
            fence(session, lease)
        given = {key: value for key, value in changes.items() if value is not None}
        late_cancel = row[1] in TERMINAL_STATUSES and given.get("status") == "cancelled"
        if row[1] == "cancelled" or late_cancel:
            given = {k: v for k, v in given.items() if k not in {"status", "result", "error"}}
        search = Search.model_validate_json(row[0]).model_copy(
            update={**given, "updated_at": utcnow()}
        )
        finishes = search.status in TERMINAL_STATUSES
        session.execute(
            "UPDATE searches SET status = ?, doc = ?, "
            "finished_at = CASE WHEN ? THEN coalesce(finished_at, ?) END WHERE id = ?",
            (
                search.status,
                search.model_dump_json(),
                finishes,
                self.database.stamp(search.updated_at),
                search_id,
            ),
        )
        if search.status == "failed" and (search.error is None or search.error.type != OUTAGE):
            session.execute("DELETE FROM images WHERE search_id = ?", (search_id,))
            session.execute("UPDATE searches SET image_bytes = 0 WHERE id = ?", (search_id,))
        self._changed(session, search_id)
        return search

    def reopen(self, search_id: str) -> Search | None:
        """Queue a failed search again: status ``queued``, its error and finish time dropped
        (it resumes from its recorded iterations); stamps ``updated_at``. None, and nothing
        changed, when it is no longer failed (another controller retried or deleted it since
        it was read: a search is reopened once, so it is run once)."""
        with self.database.write() as session:
            row = session.execute(
                "SELECT doc FROM searches WHERE id = ? AND status = 'failed'"
                + (" FOR UPDATE" if self.database.dialect == "postgresql" else ""),
                (search_id,),
            ).fetchone()
            if row is None:
                return None
            search = Search.model_validate_json(row[0]).model_copy(
                update={"status": "queued", "error": None, "updated_at": utcnow()}
            )
            session.execute(
                "UPDATE searches SET status = ?, doc = ?, finished_at = NULL WHERE id = ?",
                (search.status, search.model_dump_json(), search_id),
            )
            self._changed(session, search_id)
        return search

    def unfinished(self) -> list[str]:
        """Ids of queued and running searches, oldest first (to resume after a restart)."""
        with self.database.read() as session:
            rows = session.execute(
                f"SELECT id FROM searches WHERE status IN {_UNFINISHED} ORDER BY created_at, id"
            ).fetchall()
        return [row[0] for row in rows]

    def _time(self, stored: Any) -> datetime | None:
        return None if stored is None else self.database.when(stored)

    def usage(self, owner: str, since: datetime) -> Usage:
        """What ``owner``'s searches hold, and how many it created since ``since``."""
        with self.database.read() as session:
            active, image_bytes = session.execute(
                f"SELECT count(CASE WHEN status IN {_UNFINISHED} THEN 1 END), "
                "coalesce(sum(image_bytes), 0) FROM searches WHERE owner = ?",
                (owner,),
            ).fetchone()
            recent, first_recent = session.execute(
                "SELECT count(*), min(created_at) FROM searches "
                "WHERE owner = ? AND created_at >= ?",
                (owner, self.database.stamp(since)),
            ).fetchone()
            (first_expiry,) = session.execute(
                "SELECT min(finished_at) FROM searches "
                "WHERE owner = ? AND finished_at IS NOT NULL AND image_bytes > 0",
                (owner,),
            ).fetchone()
        return Usage(
            active=int(active),
            recent=int(recent),
            first_recent=self._time(first_recent),
            image_bytes=int(image_bytes),
            first_expiry=self._time(first_expiry),
        )

    def expire(self, finished_before: datetime, batch: int = 200) -> int:
        """Delete the searches that finished before ``finished_before``, with their images and
        iterations; how many. In batches of ``batch``, each its own transaction, so that other
        requests get the database between them. Several controllers may sweep at once: each
        deletes what it finds still there."""
        expired = 0
        before = self.database.stamp(finished_before)
        while True:
            with self.database.write() as session:
                deleted = session.execute(
                    "DELETE FROM searches WHERE id IN (SELECT id FROM searches "
                    "WHERE finished_at IS NOT NULL AND finished_at < ? LIMIT ?)",
                    (before, batch),
                ).rowcount
            expired += deleted
            if deleted < batch:
                return expired

    def size(self) -> StoreSize:
        """How many searches the store holds, their images' bytes, the database's bytes."""
        with self.database.read() as session:
            searches, image_bytes = session.execute(
                "SELECT count(*), coalesce(sum(image_bytes), 0) FROM searches"
            ).fetchone()
        return StoreSize(
            searches=int(searches),
            image_bytes=int(image_bytes),
            database_bytes=self.database.database_bytes(),
        )
