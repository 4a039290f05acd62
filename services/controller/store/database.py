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

__all__ = ["Database", "DatabaseUnavailable", "Dialect", "Rows", "Session"]

Dialect = Literal["sqlite", "postgresql"]


class DatabaseUnavailable(Exception):
    """The database cannot be reached or refuses the controller (its message is one line that
    names the setting, for an operator)."""


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
