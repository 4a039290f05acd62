"""What the controller's stores need of a database, whichever it is: sessions that run SQL, the
conversion of times, and its size. :mod:`.sqlite` and :mod:`.postgres` are the two back ends.

The stores write their SQL once, with ``?`` placeholders and the SQL both dialects share
(``INSERT … ON CONFLICT … DO UPDATE``, ``DELETE … RETURNING``, ``CAST(? AS TEXT)``); a back end
translates the placeholders to its driver's.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import AbstractContextManager
from datetime import datetime
from typing import Any, Literal, Protocol

from services.common.errors import ServiceUnavailableError

__all__ = ["RETRY_AFTER_S", "Database", "DatabaseUnavailable", "Dialect", "Rows", "Session"]

RETRY_AFTER_S = 5
"""``Retry-After`` of a request refused while the database is away."""

Dialect = Literal["sqlite", "postgresql"]


class DatabaseUnavailable(ServiceUnavailableError):
    """The database cannot be reached or refuses the controller: a request that needs it is
    answered 503 (``Retry-After``, no address in it); ``str()`` is one line for an operator,
    naming the setting and the server."""

    slug = "database-unavailable"

    def __init__(self, reason: str) -> None:
        super().__init__(
            "the controller's database does not answer; try again after Retry-After seconds",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )
        self.reason = reason

    def __str__(self) -> str:
        return self.reason


class Rows(Protocol):
    """What a statement answers (a DB-API cursor)."""

    @property
    def rowcount(self) -> int: ...

    def fetchone(self) -> Any: ...

    def fetchall(self) -> list[Any]: ...


class Session(Protocol):
    """A connection held for one block: one transaction when it writes."""

    def execute(self, sql: str, args: Sequence[Any] = ()) -> Rows: ...


class Database(Protocol):
    """One database that the search and key stores share."""

    dialect: Dialect

    def read(self) -> AbstractContextManager[Session]:
        """A session for reads (each statement sees what was committed before it)."""
        ...

    def write(self) -> AbstractContextManager[Session]:
        """A session in one transaction: committed at the end of the block, or rolled back."""
        ...

    def stamp(self, when: datetime) -> Any:
        """A UTC time as the database stores it."""
        ...

    def when(self, stored: Any) -> datetime:
        """A stored time as an aware UTC :class:`datetime`."""
        ...

    def database_bytes(self) -> int:
        """Bytes of the database in use (free pages and logs aside)."""
        ...

    def ping(self) -> None:
        """Raise :class:`DatabaseUnavailable` unless the database answers now."""
        ...

    def close(self) -> None: ...
