"""Which controller runs which search, when several share one PostgreSQL database: leases with
a heartbeat, and fencing by the lease's generation.

A controller runs a search only under a lease: a row ``(search, holder, generation,
expires_at)``. It takes the lease of a search it was submitted as it records it, when it can
start it at once (:meth:`Leases.hold`, in the recording's transaction, so that no other
controller claims the new search first), or when a worker starts it (:meth:`Leases.take`), claims
the unfinished searches whose lease ran out (:meth:`Leases.claim`, ``FOR UPDATE … SKIP LOCKED``,
so that controllers claiming at once never wait for, nor take, the same search) and renews what
it holds every third of the lease time (:meth:`Leases.renew`). Every claim adds one to the
generation, and every write of a run carries the generation it holds (:func:`fence`, in the
write's transaction, under ``FOR SHARE`` of the lease row, so a claim waits for a write in
flight): a controller that was cut off and comes back finds its generation stale, and its writes
are refused, so no iteration is recorded twice. A released lease keeps its row (expired at once)
and its generation, so a search retried later never hands out a generation again. Expiry is
judged by the database's clock (``now()``), never by the controllers'.

A controller that dies is replaced within ``lease_s`` of its last heartbeat plus one claim
period (``lease_s / 3``); the taker resumes the search from its last recorded iteration.

Why not a job library: procrastinate and pgqueuer run *jobs*, functions called with arguments,
to an end; retries re-run the whole job and neither fences the writes of a worker that lost its
lock (procrastinate marks stalled jobs by heartbeat, pgqueuer by a lock timeout; the stale
worker's writes still land). A search here is a row with its own state machine (queued, running,
cancelled, retried) read by the API, resumed from its last iteration, and its writes must be
refused once another controller holds it. What is needed is one table, three statements and a
check in each write's transaction, smaller than either library's schema and worker loop, with the
fencing that neither gives.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.controller.store.database import Database, Session

__all__ = ["FIRST_GENERATION", "Lease", "LeaseLost", "Leases", "fence"]

FIRST_GENERATION = 1
"""The generation of a search's first lease (:data:`_CLAIM` and :meth:`Leases.hold`)."""


@dataclass(frozen=True)
class Lease:
    """A controller's right to run a search: refused once a later generation exists."""

    search_id: str
    generation: int


class LeaseLost(Exception):
    """A write of a run whose lease is no longer the search's (another controller took it)."""


def fence(session: Session, lease: Lease) -> None:
    """Raise :class:`LeaseLost` unless ``lease`` is the newest of its search; holds the lease
    row (``FOR SHARE``) until the transaction of ``session`` ends."""
    row = session.execute(
        "SELECT generation FROM leases WHERE search_id = ? FOR SHARE", (lease.search_id,)
    ).fetchone()
    if row is None or int(row[0]) != lease.generation:
        raise LeaseLost(
            f"search {lease.search_id}: lease generation {lease.generation} is stale "
            f"(now {None if row is None else row[0]})"
        )


_CLAIM = """
WITH free AS (
    SELECT s.id FROM searches s LEFT JOIN leases l ON l.search_id = s.id
    WHERE s.status IN ('queued', 'running') AND (l.search_id IS NULL OR l.expires_at < now())
    {only}
    ORDER BY s.created_at, s.id
    LIMIT ?
    FOR UPDATE OF s SKIP LOCKED
)
INSERT INTO leases (search_id, holder, generation, expires_at)
SELECT id, ?, 1, now() + make_interval(secs => ?) FROM free
ON CONFLICT (search_id) DO UPDATE SET
    holder = excluded.holder,
    generation = leases.generation + 1,
    expires_at = excluded.expires_at
WHERE leases.expires_at < now()
RETURNING search_id, generation
"""


class Leases:
    """The leases of one controller (``holder``) on a PostgreSQL database."""

    def __init__(self, database: Database, holder: str, lease_s: float) -> None:
        if database.dialect != "postgresql":
            raise ValueError("leases need PostgreSQL: a SQLite database has one controller")
        if lease_s <= 0:
            raise ValueError("lease_s must be positive")
        self.database = database
        self.holder = holder
        self.lease_s = lease_s

    def hold(self, session: Session, search_id: str) -> Lease:
        """Take the first lease of the search ``session`` records (it has no lease row yet), in
        that transaction: the search is never unleased once committed."""
        session.execute(
            "INSERT INTO leases (search_id, holder, generation, expires_at) "
            "VALUES (?, ?, ?, now() + make_interval(secs => ?))",
            (search_id, self.holder, FIRST_GENERATION, self.lease_s),
        )
        return Lease(search_id, FIRST_GENERATION)

    def claim(self, limit: int) -> list[Lease]:
        """Take up to ``limit`` unfinished searches that no live lease holds, oldest first."""
        if limit <= 0:
            return []
        with self.database.write() as session:
            rows = session.execute(
                _CLAIM.format(only=""), (limit, self.holder, self.lease_s)
            ).fetchall()
        return [Lease(row[0], int(row[1])) for row in rows]

    def take(self, search_id: str) -> Lease | None:
        """The lease of one unfinished search, unless a live one holds it (or it is being
        written to at this moment, or finished)."""
        with self.database.write() as session:
            row = session.execute(
                _CLAIM.format(only="AND s.id = ?"), (search_id, 1, self.holder, self.lease_s)
            ).fetchone()
        return None if row is None else Lease(row[0], int(row[1]))

    def renew(self, held: list[Lease]) -> list[Lease]:
        """Extend the leases in ``held`` that are still this controller's and whose searches
        are unfinished; those (the others were taken over, or cancelled, or deleted)."""
        if not held:
            return []
        with self.database.write() as session:
            rows = session.execute(
                "UPDATE leases l SET expires_at = now() + make_interval(secs => ?) "
                "FROM searches s WHERE s.id = l.search_id AND l.holder = ? "
                "AND l.search_id = ANY(?) AND s.status IN ('queued', 'running') "
                "RETURNING l.search_id, l.generation",
                (self.lease_s, self.holder, [lease.search_id for lease in held]),
            ).fetchall()
        renewed = {(row[0], int(row[1])) for row in rows}
        return [lease for lease in held if (lease.search_id, lease.generation) in renewed]

    def release(self, lease: Lease) -> None:
        """Give the search up (its run ended): another controller may claim it at once, with
        the next generation."""
        with self.database.write() as session:
            session.execute(
                "UPDATE leases SET expires_at = now() WHERE search_id = ? AND generation = ?",
                (lease.search_id, lease.generation),
            )
