"""PostgreSQL on a host of its own, and what the hosts test reads of it directly.

The server is :class:`tests.postgres_server.PostgresServer` (Debian's binaries, installed when
missing), started inside the host's namespace on its address and open to the network's
addresses. :func:`record_writes` adds a trigger that logs every write of an iteration (insert or
update) to a table of its own: the store replaces an iteration of the same index without a
trace, so "no iteration recorded twice" is checked in the database, not in what the API shows.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import psycopg

from tests.hosts.network import Host, Network
from tests.postgres_server import PostgresServer, postgres_problem

__all__ = ["Ledger", "start_postgres"]

_LOG_WRITES = """
CREATE TABLE iteration_writes (search_id TEXT NOT NULL, idx INTEGER NOT NULL, op TEXT NOT NULL);
CREATE FUNCTION log_iteration_write() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    INSERT INTO iteration_writes VALUES (NEW.search_id, NEW.idx, TG_OP);
    RETURN NEW;
END $$;
CREATE TRIGGER iteration_written AFTER INSERT OR UPDATE ON iterations
    FOR EACH ROW EXECUTE FUNCTION log_iteration_write();
"""


def start_postgres(network: Network, name: str = "postgres") -> tuple[Host, str] | str:
    """A PostgreSQL server on a new host ``name`` (stopped when the network closes) and the
    URL of a fresh database on it; or why it cannot be had."""
    binaries, why = postgres_problem()
    if binaries is None:
        return why or "no PostgreSQL"
    host = network.add_host(name)
    server = PostgresServer(
        binaries, address=host.address, inside=host.prefix, clients=network.addressing.cidr
    )
    network.on_close(server.stop)
    return host, server.new_database()


@dataclass(frozen=True)
class Ledger:
    """What the database at ``url`` says of the searches and their iterations."""

    url: str

    def record_writes(self) -> None:
        """Log every iteration written from now on (the schema must exist: a controller ran)."""
        with psycopg.connect(self.url, autocommit=True) as db:
            db.execute(_LOG_WRITES)

    def written_twice(self) -> list[tuple[str, int, int]]:
        """(search, index, times) of each iteration written more than once."""
        with psycopg.connect(self.url, autocommit=True) as db:
            rows = db.execute(
                "SELECT search_id, idx, count(*) FROM iteration_writes "
                "GROUP BY search_id, idx HAVING count(*) > 1 ORDER BY 1, 2"
            ).fetchall()
        return [(row[0], int(row[1]), int(row[2])) for row in rows]

    def writes(self) -> int:
        with psycopg.connect(self.url, autocommit=True) as db:
            return int(db.execute("SELECT count(*) FROM iteration_writes").fetchone()[0])

    def holders(self) -> dict[str, tuple[str, int]]:
        """Each search's lease: its holder and generation."""
        with psycopg.connect(self.url, autocommit=True) as db:
            rows = db.execute("SELECT search_id, holder, generation FROM leases").fetchall()
        return {row[0]: (row[1], int(row[2])) for row in rows}

    def held_by(self, pid: int) -> set[str]:
        """The unfinished searches whose live lease the controller process ``pid`` holds (a
        holder is named ``host:pid:random``)."""
        with psycopg.connect(self.url, autocommit=True) as db:
            rows = db.execute(
                "SELECT l.search_id FROM leases l JOIN searches s ON s.id = l.search_id "
                "WHERE s.status IN ('queued', 'running') AND l.expires_at > now() "
                "AND split_part(l.holder, ':', 2) = %s",
                (str(pid),),
            ).fetchall()
        return {row[0] for row in rows}

    def runs_by_holder(self) -> Counter[str]:
        """How many searches each controller process (by pid) holds the last lease of."""
        return Counter(holder.split(":")[1] for holder, _ in self.holders().values())
