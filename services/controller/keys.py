"""API keys of the controller's public API: created, listed, revoked, and checked, in the
controller's database (SQLite or PostgreSQL, :mod:`services.controller.store`).

A key is ``cosmos_`` and 43 URL-safe characters from :func:`secrets.token_urlsafe` (256 random
bits). Only its SHA-256 is stored, never the key: a plain hash is enough because the key is
random, not chosen by a person. A slow password hash (bcrypt, argon2) exists to make guessing a
low-entropy password expensive; no guessing finds a 256-bit key, and a fast hash keeps checking
one request's key at one indexed lookup. The lookup is by hash, so how long it takes says nothing
about the key.

Each key has a public id (what ``cosmos keys list`` and ``revoke`` show and take, and what owns
the key's searches), a name, and whether it is an admin key (sees every tenant's searches, has
no quotas). A revoked key stays listed, with when it was revoked, and is refused from then on.

The local key (:func:`local_key`) is how ``cosmos up``, ``cosmos demo`` and the tests work
without set-up: an admin key named ``local``, kept in :data:`KEY_FILE` beside the controller's
database (``data/api-key`` for the default database), created on first use and reused while it
is valid. Clients (:func:`client_key`) take ``COSMOS_API_KEY`` when set, else that file.
"""

from __future__ import annotations

import hashlib
import os
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from services.common.settings import API_KEY_VARIABLE
from services.controller.store import Database, database_path, is_postgres_url, open_database

__all__ = [
    "API_KEY_VARIABLE",
    "KEY_FILE",
    "ApiKey",
    "KeyStore",
    "client_key",
    "hash_key",
    "key_file",
    "local_key",
    "new_key",
    "rooted",
]

KEY_FILE = "api-key"
"""The local key's file name, in the folder of the controller's database."""

_PREFIX = "cosmos_"


@dataclass(frozen=True)
class ApiKey:
    """A key as stored (its hash aside): who a request acts for."""

    id: str
    name: str
    admin: bool
    created_at: datetime
    revoked_at: datetime | None = None


def new_key() -> str:
    """A fresh random key (256 bits)."""
    return _PREFIX + secrets.token_urlsafe(32)


def hash_key(key: str) -> str:
    """The SHA-256 of ``key`` (hex), as stored; see the module's docstring for why no KDF."""
    return hashlib.sha256(key.encode()).hexdigest()


_COLUMNS = "id, name, admin, created_at, revoked_at"


class KeyStore:
    """The API keys in the controller's database (a :class:`Database`, or the URL of one it
    opens and closes); safe to share between threads. The controllers and ``cosmos keys`` open
    the same database: a key revoked by one is refused by the others on their next request."""

    def __init__(self, database: Database | str) -> None:
        self._owned = isinstance(database, str)
        self.database = open_database(database) if isinstance(database, str) else database

    def close(self) -> None:
        if self._owned:
            self.database.close()

    def _key_of(self, row: Any) -> ApiKey:
        return ApiKey(
            id=row[0],
            name=row[1],
            admin=bool(row[2]),
            created_at=self.database.when(row[3]),
            revoked_at=None if row[4] is None else self.database.when(row[4]),
        )

    def create(self, name: str, *, admin: bool = False) -> tuple[ApiKey, str]:
        """A new key: its record and the key itself, which is not stored and cannot be shown
        again."""
        if not name.strip() or len(name) > 100:
            raise ValueError("a key's name must be 1 to 100 characters")
        key = new_key()
        record = ApiKey(
            id=secrets.token_hex(6), name=name.strip(), admin=admin, created_at=datetime.now(UTC)
        )
        with self.database.write() as session:
            session.execute(
                "INSERT INTO api_keys (id, name, sha256, admin, created_at) VALUES (?, ?, ?, ?, ?)",
                (
                    record.id,
                    record.name,
                    hash_key(key),
                    admin,
                    self.database.stamp(record.created_at),
                ),
            )
        return record, key

    def all(self) -> list[ApiKey]:
        """Every key, revoked ones too, oldest first."""
        with self.database.read() as session:
            rows = session.execute(f"SELECT {_COLUMNS} FROM api_keys ORDER BY created_at, id")
            return [self._key_of(row) for row in rows.fetchall()]

    def get(self, key_id: str) -> ApiKey | None:
        with self.database.read() as session:
            row = session.execute(
                f"SELECT {_COLUMNS} FROM api_keys WHERE id = ?", (key_id,)
            ).fetchone()
        return None if row is None else self._key_of(row)

    def revoke(self, key_id: str) -> ApiKey:
        """Refuse the key from now on (a revoked key stays revoked); KeyError if unknown."""
        with self.database.write() as session:
            session.execute(
                "UPDATE api_keys SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL",
                (self.database.stamp(datetime.now(UTC)), key_id),
            )
        key = self.get(key_id)
        if key is None:
            raise KeyError(key_id)
        return key

    def verify(self, key: str) -> ApiKey | None:
        """The key's record if ``key`` is a key of this store and not revoked, else None."""
        with self.database.read() as session:
            row = session.execute(
                f"SELECT {_COLUMNS} FROM api_keys WHERE sha256 = ? AND revoked_at IS NULL",
                (hash_key(key),),
            ).fetchone()
        return None if row is None else self._key_of(row)


def rooted(database_url: str, root: Path) -> str:
    """``database_url`` with a relative path taken from ``root`` (where the services run)."""
    prefix = "sqlite:///"
    path = database_url.removeprefix(prefix)
    if (
        not database_url.startswith(prefix)  # refused by the store, with the reason
        or path in {"", ":memory:"}
        or Path(path).expanduser().is_absolute()
    ):
        return database_url
    return f"{prefix}{root / path}"


def key_file(database_url: str) -> Path:
    """Where the local key of the controller whose database is ``database_url`` is kept (a
    SQLite file's folder; a PostgreSQL database has none)."""
    if is_postgres_url(database_url):
        raise ValueError(
            "a PostgreSQL controller database has no local key file: create a key with "
            "cosmos keys create and give it to clients as COSMOS_API_KEY"
        )
    path = database_path(database_url)
    if path == ":memory:":
        raise ValueError(
            "an in-memory controller database keeps no keys another process can read; give "
            "COSMOS_CONTROLLER_DATABASE_URL a file, or turn auth off (COSMOS_CONTROLLER_AUTH=off)"
        )
    return Path(path).expanduser().parent / KEY_FILE


def local_key(database_url: str) -> str:
    """The local admin key of the database at ``database_url``: the one in its key file while
    that is a valid key of the database, else a new one, written there (readable by this user
    only)."""
    path = key_file(database_url)
    keys = KeyStore(database_url)
    try:
        if path.exists():
            kept = path.read_text().strip()
            if kept and keys.verify(kept) is not None:
                return kept
        _, key = keys.create("local", admin=True)
    finally:
        keys.close()
    fresh = path.with_name(f".{KEY_FILE}.{os.getpid()}")
    fd = os.open(fresh, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(key + "\n")
    fresh.replace(path)
    return key


def client_key(database_url: str, environ: Mapping[str, str] | None = None) -> str | None:
    """The key a client sends: ``COSMOS_API_KEY`` when set, else the local key file of the
    database at ``database_url`` when there is one, else None."""
    environ = os.environ if environ is None else environ
    given = environ.get(API_KEY_VARIABLE, "").strip()
    if given:
        return given
    try:
        path = key_file(database_url)
    except ValueError:
        return None
    if not path.is_file():
        return None
    return path.read_text().strip() or None
