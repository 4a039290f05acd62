"""The controller's database: searches (:mod:`.searches`) and API keys
(:mod:`services.controller.keys`) in SQLite (:mod:`.sqlite`, one controller) or PostgreSQL
(:mod:`.postgres`, several controllers, with :mod:`.leases`), behind one
:class:`~.database.Database` interface; the schema is versioned (:mod:`.migrations`).

``COSMOS_CONTROLLER_DATABASE_URL`` chooses: ``sqlite:///path`` or ``postgresql://…``
(:func:`open_database`).
"""

from __future__ import annotations

from services.controller.store.database import Database, DatabaseUnavailable
from services.controller.store.leases import FIRST_GENERATION, Lease, LeaseLost, Leases
from services.controller.store.postgres import PostgresDatabase, is_postgres_url
from services.controller.store.searches import (
    SearchChanges,
    SearchStore,
    StoreSize,
    Usage,
    utcnow,
)
from services.controller.store.sqlite import SqliteDatabase, database_path

__all__ = [
    "FIRST_GENERATION",
    "Database",
    "DatabaseUnavailable",
    "Lease",
    "LeaseLost",
    "Leases",
    "PostgresDatabase",
    "SearchChanges",
    "SearchStore",
    "SqliteDatabase",
    "StoreSize",
    "Usage",
    "database_path",
    "is_postgres_url",
    "open_database",
    "open_store",
    "utcnow",
]


def open_database(
    url: str,
    *,
    checkpoint_every_s: float = 1.0,
    connect_timeout_s: float = 5.0,
    dead_after_s: float = 5.0,
) -> Database:
    """The database of ``url``, migrated: PostgreSQL for ``postgresql://`` (a connection left
    without an answer for ``dead_after_s`` is given up), else SQLite (``sqlite:///path``;
    anything else is refused, naming the setting)."""
    if is_postgres_url(url):
        return PostgresDatabase(url, connect_timeout_s=connect_timeout_s, dead_after_s=dead_after_s)
    return SqliteDatabase(url, checkpoint_every_s=checkpoint_every_s)


def open_store(url: str, *, checkpoint_every_s: float = 1.0) -> SearchStore:
    """A search store on a database of its own (:func:`open_database`), closed with it."""
    return SearchStore(open_database(url, checkpoint_every_s=checkpoint_every_s))
