"""Events: change notifications per search (in process, and from the other controllers on a
shared PostgreSQL database, no polling), and the two streams of
server-sent events they feed, a search's (``GET /searches/{id}/events``) and the health's
(``GET /health/events``), served with sse-starlette."""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import contextmanager
from typing import Final

from sse_starlette import EventSourceResponse, ServerSentEvent

from services.common.contracts.search import TERMINAL_STATUSES
from services.common.stopping import STOPPING
from services.controller.store import SearchStore

__all__ = [
    "HEALTH_EVENTS_EVERY_S",
    "KEEP_ALIVE_S",
    "Notifier",
    "event_stream",
    "health_events",
    "search_events",
]


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

    def publish_all(self) -> None:
        """Wake every waiter (changes may have been missed: they read the store again)."""
        events, self._events = self._events, {}
        for event in events.values():
            event.set()

    def followed(self) -> int:
        """How many searches have followers or an event waiting (0 when nobody follows)."""
        return len(self._events.keys() | self._followers.keys())


KEEP_ALIVE_S: Final = 15.0
"""A comment (``: keep-alive``) goes out on an event stream this often, so that proxies keep it
open. sse-starlette sends it on a timer of its own, also between events (the home-made streams
sent it after 15 s without one); a client skips comments either way."""
HEALTH_EVENTS_EVERY_S: Final = 1.0
"""How often ``GET /health/events`` looks whether the health changed."""
STOP_CHECK_S: Final = 1.0
"""How often a waiting event stream looks whether the server is stopping (:data:`STOPPING`)."""
_SEP: Final = "\n"
"""Lines end in LF, as they did before sse-starlette (whose default is CRLF)."""


def _event(name: str, data: str) -> ServerSentEvent:
    return ServerSentEvent(data, event=name, sep=_SEP)


def _keep_alive() -> ServerSentEvent:
    return ServerSentEvent(comment="keep-alive", sep=_SEP)


def event_stream(events: AsyncIterator[ServerSentEvent]) -> EventSourceResponse:
    """``events`` as ``text/event-stream``, with a keep-alive comment every 15 s and
    ``Cache-Control: no-cache``; the stream ends where ``events`` does (a client that leaves
    cancels it). GZipMiddleware leaves ``text/event-stream`` alone."""
    return EventSourceResponse(
        events,
        headers={"Cache-Control": "no-cache"},
        ping=KEEP_ALIVE_S,
        sep=_SEP,
        ping_message_factory=_keep_alive,
    )


async def _set_within(event: asyncio.Event, timeout_s: float) -> bool:
    """Whether ``event`` is set within ``timeout_s``."""
    try:
        await asyncio.wait_for(event.wait(), timeout=timeout_s)
    except TimeoutError:
        return False
    return True


async def health_events(
    health: Callable[[], Awaitable[str]],
) -> AsyncIterator[ServerSentEvent]:
    """``health``, the health document ``health()`` gives, at once and then whenever it changed
    (looked at every :data:`HEALTH_EVENTS_EVERY_S`), until the server stops."""
    last = ""
    while not STOPPING.is_set():
        doc = await health()
        if doc != last:
            last = doc
            yield _event("health", doc)
        await asyncio.sleep(HEALTH_EVENTS_EVERY_S)


async def search_events(
    store: SearchStore, notifier: Notifier, search_id: str
) -> AsyncIterator[ServerSentEvent]:
    """A search's events (:data:`~services.common.contracts.search.SEARCH_EVENTS`): while it is
    queued or running, ``search`` with the search without its iterations whenever it changed;
    ``iteration`` for each recorded iteration; then one ``end`` with the search without its
    iterations. The stored JSON documents are sent as they are. Ends when the server stops (the
    client follows again, elsewhere). A search another controller runs (PostgreSQL) wakes
    its followers here through the database's notifications
    (:mod:`~services.controller.store.changes`; a listener that reconnects wakes them all).
    The event is taken before the store is read, so a change committed meanwhile is not
    missed. (They once seemed to be missed in one test run in three: that was another
    controller claiming the search first and running it with a longer outage budget.)"""
    sent = 0
    last_doc = ""
    with notifier.following(search_id):  # a client that goes away stops following
        while True:
            changed = notifier.current(search_id)
            # The status before the iterations: a search ends after its last one.
            # On threads: a database that hangs holds this stream, not the event loop.
            status_doc = await asyncio.to_thread(store.status_doc, search_id)
            if status_doc is not None and status_doc[0] not in TERMINAL_STATUSES:
                if status_doc[1] != last_doc:
                    last_doc = status_doc[1]
                    yield _event("search", last_doc)
            docs = await asyncio.to_thread(store.iteration_docs, search_id, start=sent)
            for doc in docs:
                yield _event("iteration", doc)
            sent += len(docs)
            if status_doc is None:  # expired meanwhile: stop rather than spin
                return
            if status_doc[0] in TERMINAL_STATUSES:
                yield _event("end", status_doc[1])
                return
            while not await _set_within(changed, STOP_CHECK_S):
                if STOPPING.is_set():
                    return  # the server is stopping: the client follows again elsewhere
