"""Change notifications per search, for server-sent events (in process, no polling)."""

from __future__ import annotations

import asyncio

__all__ = ["Notifier"]


class Notifier:
    """Wakes every waiter of a search when it changes."""

    def __init__(self) -> None:
        self._events: dict[str, asyncio.Event] = {}

    def current(self, search_id: str) -> asyncio.Event:
        """The event the next change of ``search_id`` will set (take it before reading state)."""
        return self._events.setdefault(search_id, asyncio.Event())

    def publish(self, search_id: str) -> None:
        """Wake the waiters of ``search_id``."""
        event = self._events.pop(search_id, None)
        if event is not None:
            event.set()
