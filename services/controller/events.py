"""Change notifications per search, for server-sent events (in process, no polling)."""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Notifier"]


class Notifier:
    """Wakes every waiter of a search when it changes.

    A waiter follows a search inside :meth:`following`; the search's event lives only while
    someone follows it, so followers that come and go (or are cancelled) leave nothing behind.
    """

    def __init__(self) -> None:
        self._events: dict[str, asyncio.Event] = {}
        self._followers: Counter[str] = Counter()

    @contextmanager
    def following(self, search_id: str) -> Iterator[None]:
        """Follow ``search_id`` for the duration of the block (also left on cancellation)."""
        self._followers[search_id] += 1
        try:
            yield
        finally:
            self._followers[search_id] -= 1
            if self._followers[search_id] <= 0:
                del self._followers[search_id]
                self._events.pop(search_id, None)

    def current(self, search_id: str) -> asyncio.Event:
        """The event the next change of ``search_id`` will set (take it before reading state,
        inside :meth:`following`)."""
        return self._events.setdefault(search_id, asyncio.Event())

    def publish(self, search_id: str) -> None:
        """Wake the waiters of ``search_id``."""
        event = self._events.pop(search_id, None)
        if event is not None:
            event.set()

    def followed(self) -> int:
        """How many searches have followers or an event waiting (0 when nobody follows)."""
        return len(self._events.keys() | self._followers.keys())
