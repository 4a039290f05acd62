"""The controller database's schema, as numbered migrations applied in order at start-up.

Each migration has a step per dialect (SQL statements, a function, or nothing); the versions
applied are rows of ``schema_migrations``, and opening a database applies the missing ones in
one transaction (PostgreSQL: under an advisory lock, so that controllers starting together
migrate once). Both back ends share the numbers: a database is at version *n* on either.

Why not Alembic: it drives SQLAlchemy engines, a second database layer beside the ``sqlite3``
and psycopg connections the stores use, for six migrations of plain SQL. What it would add here
(auto-generated diffs, down-migrations, branches) the controller does not use; this runner is
the version table, a lock and a loop.

SQLite databases made before the schema was versioned have no ``schema_migrations``: they are at
version 0 whatever they hold, so steps 1-3 look at their columns (an older one still kept each
target image in its search's row, and had no owner, finish time or image size).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from services.common.contracts.search import Search
from services.controller.store.database import Database, Session

__all__ = ["MIGRATIONS", "Migration", "migrate", "schema_version"]

Step = str | Callable[[Session, Database], None] | None


@dataclass(frozen=True)
class Migration:
    version: int
    name: str
    sqlite: Step
    postgresql: Step


def _columns(session: Session) -> set[str]:
    return {row[1] for row in session.execute("PRAGMA table_info(searches)").fetchall()}


def _move_images(session: Session, database: Database) -> None:
    """Move target images out of the search rows (SQLite databases before version 2)."""
    if "image" not in _columns(session):
        return
    session.execute(
        "INSERT OR IGNORE INTO images (search_id, image) SELECT id, image FROM searches"
    )
    session.execute("ALTER TABLE searches DROP COLUMN image")


_ADDED_COLUMNS = {
    "owner": "TEXT",
    "finished_at": "TEXT",
    "image_bytes": "INTEGER NOT NULL DEFAULT 0",
}


def _add_columns(session: Session, database: Database) -> None:
    """Give each search an owner, finish time and image size (SQLite databases before version
    3): their searches have no owner (only admin keys see them), finished ones finished when
    last updated, failed ones lose their images as they would have on failing."""
    missing = [name for name in _ADDED_COLUMNS if name not in _columns(session)]
    if not missing:
        return
    for name in missing:
        session.execute(f"ALTER TABLE searches ADD COLUMN {name} {_ADDED_COLUMNS[name]}")
    finished = session.execute(
        "SELECT id, doc FROM searches WHERE status IN ('succeeded', 'failed', 'cancelled')"
    ).fetchall()
    for search_id, doc in finished:
        updated = Search.model_validate_json(doc).updated_at
        session.execute(
            "UPDATE searches SET finished_at = ? WHERE id = ?", (database.stamp(updated), search_id)
        )
    session.execute(
        "DELETE FROM images WHERE search_id IN (SELECT id FROM searches WHERE status = 'failed')"
    )
    session.execute(
        "UPDATE searches SET image_bytes = coalesce("
        "(SELECT length(image) FROM images WHERE search_id = searches.id), 0)"
    )


_INDEXES = """
CREATE INDEX IF NOT EXISTS searches_created ON searches (created_at DESC);
CREATE INDEX IF NOT EXISTS searches_owner_created ON searches (owner, created_at);
CREATE INDEX IF NOT EXISTS searches_owner_status ON searches (owner, status, image_bytes);
CREATE INDEX IF NOT EXISTS searches_finished ON searches (finished_at)
    WHERE finished_at IS NOT NULL
"""

MIGRATIONS: tuple[Migration, ...] = (
    Migration(
        1,
        "searches, their target images and iterations",
        sqlite="""
        CREATE TABLE IF NOT EXISTS searches (
            id TEXT PRIMARY KEY, status TEXT NOT NULL, created_at TEXT NOT NULL, doc TEXT NOT NULL
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
        )
        """,
        postgresql="""
        CREATE TABLE searches (
            id TEXT PRIMARY KEY,
            status TEXT NOT NULL,
            created_at TIMESTAMPTZ NOT NULL,
            doc TEXT NOT NULL,
            owner TEXT,
            finished_at TIMESTAMPTZ,
            image_bytes BIGINT NOT NULL DEFAULT 0
        );
        CREATE TABLE images (
            search_id TEXT PRIMARY KEY REFERENCES searches (id) ON DELETE CASCADE,
            image BYTEA NOT NULL
        );
        CREATE TABLE iterations (
            search_id TEXT NOT NULL REFERENCES searches (id) ON DELETE CASCADE,
            idx INTEGER NOT NULL,
            doc TEXT NOT NULL,
            PRIMARY KEY (search_id, idx)
        )
        """,
    ),
    Migration(2, "target images out of the search rows", sqlite=_move_images, postgresql=None),
    Migration(3, "owners, finish times and image sizes", sqlite=_add_columns, postgresql=None),
    Migration(4, "indexes of the searches", sqlite=_INDEXES, postgresql=_INDEXES),
    Migration(
        5,
        "API keys",
        sqlite="""
        CREATE TABLE IF NOT EXISTS api_keys (
            id TEXT PRIMARY KEY,
            name TEXT NOT NULL,
            sha256 TEXT NOT NULL UNIQUE,
            admin INTEGER NOT NULL,
            created_at TEXT NOT NULL,
            revoked_at TEXT
        )
        """,
        postgresql="""
        CREATE TABLE api_keys (
            id TEXT PRIMARY KEY,
            name TEXT NOT NULL,
            sha256 TEXT NOT NULL UNIQUE,
            admin BOOLEAN NOT NULL,
            created_at TIMESTAMPTZ NOT NULL,
            revoked_at TIMESTAMPTZ
        )
        """,
    ),
    Migration(
        6,
        "leases of the searches being run",
        sqlite=None,  # one controller per SQLite database: it runs every search itself
        postgresql="""
        CREATE TABLE leases (
            search_id TEXT PRIMARY KEY REFERENCES searches (id) ON DELETE CASCADE,
            holder TEXT NOT NULL,
            generation BIGINT NOT NULL,
            expires_at TIMESTAMPTZ NOT NULL
        );
        CREATE INDEX leases_expiry ON leases (expires_at)
        """,
    ),
)
"""Every migration, oldest first; a new one goes at the end with the next number."""


def _statements(sql: str) -> list[str]:
    return [part.strip() for part in sql.split(";") if part.strip()]


def schema_version(session: Session) -> int:
    """The newest migration applied (0 for none)."""
    row = session.execute("SELECT coalesce(max(version), 0) FROM schema_migrations").fetchone()
    return int(row[0])


def migrate(database: Database, session: Session) -> list[int]:
    """Apply the migrations ``database`` lacks, in the transaction of ``session``; their
    versions."""
    session.execute(
        "CREATE TABLE IF NOT EXISTS schema_migrations "
        "(version INTEGER PRIMARY KEY, name TEXT NOT NULL)"
    )
    current = schema_version(session)
    applied = []
    for migration in MIGRATIONS:
        if migration.version <= current:
            continue
        step = migration.sqlite if database.dialect == "sqlite" else migration.postgresql
        if isinstance(step, str):
            for statement in _statements(step):
                session.execute(statement)
        elif step is not None:
            step(session, database)
        session.execute(
            "INSERT INTO schema_migrations (version, name) VALUES (?, ?)",
            (migration.version, migration.name),
        )
        applied.append(migration.version)
    return applied
