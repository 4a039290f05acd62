"""LRU caches shared between threads: ``cachetools.LRUCache`` under a lock, counting hits.

``cachetools.LRUCache`` stores, bounds and evicts, by entries or, with ``getsizeof``, by bytes:
what the optimizer caches varies in size (one view predicted into every pose of a 25,000-pose
grid weighs megabytes, the controller's views carry their film), so a count says little about
memory there. :class:`SharedLru` is a thin wrapper that adds what cachetools leaves to its
caller, and nothing else:

* a lock: cachetools is not thread-safe, and the optimizer's strategies run on worker threads,
  the renderer's scene cache is filled on its Mitsuba thread and read on the event loop;
* hits and misses, counted for the tests and benchmarks that show a cache hits;
* :meth:`SharedLru.get` computes a missing value outside the lock (two threads may compute one
  value at once, never wait for each other) and stores it;
* a value heavier than the whole bound is answered but not kept (cachetools raises
  ``ValueError``), so a bound of 0 keeps nothing;
* a byte bound counts :data:`ENTRY_OVERHEAD` per entry besides the value's ``weigh``, so that
  array-free values are bounded too.

A caller whose values a coroutine computes uses :meth:`SharedLru.lookup` and
:meth:`SharedLru.put` around its ``await``; two requests for one key not kept may then both
compute it (no single flight: the callers' values are the same either way). A domain cache
that answers in its own terms (the optimizer's view mappings, the controller's view store)
derives from :class:`LruFront`, which forwards the counters and the size.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Hashable
from typing import Final, Generic, TypeVar

import cachetools
import numpy as np

__all__ = ["ENTRY_OVERHEAD", "LruFront", "SharedLru", "array_nbytes"]

V = TypeVar("V")

ENTRY_OVERHEAD: Final = 256
"""Bytes an entry of a byte-bounded cache counts besides its ``weigh``."""

_MISSING: Final = object()


def array_nbytes(*parts: object) -> int:
    """Bytes of the numpy arrays among ``parts``: arrays themselves, the array fields of
    dataclasses, and those inside tuples and lists, each array counted once."""
    seen: set[int] = set()
    total = 0
    stack = list(parts)
    while stack:
        part = stack.pop()
        if isinstance(part, np.ndarray):
            if id(part) not in seen:
                seen.add(id(part))
                total += part.nbytes
        elif isinstance(part, tuple | list):
            stack.extend(part)
        elif dataclasses.is_dataclass(part) and not isinstance(part, type):
            stack.extend(getattr(part, f.name) for f in dataclasses.fields(part))
    return total


class SharedLru(Generic[V]):
    """Values by key, least recently used first out: at most ``maxsize`` entries, or, with
    ``weigh``, at most ``maxsize`` bytes (each entry ``weigh(value) +`` :data:`ENTRY_OVERHEAD`).

    Values are shared by every caller that asks for the same key: nobody may change them.
    """

    def __init__(self, maxsize: int, weigh: Callable[[V], int] | None = None) -> None:
        if maxsize < 0:
            raise ValueError(f"maxsize must be >= 0, got {maxsize}")
        self.hits = 0
        self.misses = 0
        self._lock = threading.Lock()
        self._entries: cachetools.LRUCache[Hashable, V]
        if weigh is None:
            self._entries = cachetools.LRUCache(maxsize)
        else:
            weighed = weigh  # bound for the closure, which mypy does not narrow

            def getsizeof(value: V) -> int:
                return weighed(value) + ENTRY_OVERHEAD

            self._entries = cachetools.LRUCache(maxsize, getsizeof=getsizeof)

    @property
    def maxsize(self) -> int:
        """The bound: entries, or bytes with ``weigh``."""
        return int(self._entries.maxsize)

    @property
    def currsize(self) -> int:
        """What is held now, in the bound's unit (never more than :attr:`maxsize`)."""
        return int(self._entries.currsize)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        """Whether ``key`` is kept (neither a hit nor a miss, and not made recent)."""
        with self._lock:
            return key in self._entries

    def keys(self) -> tuple[Hashable, ...]:
        """The keys kept now, least recently used first."""
        with self._lock:
            return tuple(self._entries)

    def lookup(self, key: Hashable) -> V | None:
        """The stored value of ``key`` (now the most recently used), else None; counted as a
        hit or a miss. (A cache whose values may be None tells them apart with :meth:`get`.)"""
        found = self._find(key)
        return None if found is _MISSING else found  # type: ignore[return-value]

    def get(self, key: Hashable, compute: Callable[[], V]) -> V:
        """The value of ``key``: the stored one, else ``compute()`` (stored when it fits)."""
        found = self._find(key)
        if found is not _MISSING:
            return found  # type: ignore[return-value]
        value = compute()  # outside the lock: other threads never wait on it
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: V) -> bool:
        """Store ``value`` as ``key``'s (replacing any), the least recently used entries going
        until the total fits; False (and nothing stored) when it alone exceeds the bound."""
        with self._lock:
            try:
                self._entries[key] = value
            except ValueError:  # cachetools: "value too large"
                return False
        return True

    def _find(self, key: Hashable) -> object:
        """``key``'s value, made the most recently used, counting a hit or a miss."""
        with self._lock:
            found = self._entries.get(key, _MISSING)
            if found is _MISSING:
                self.misses += 1
            else:
                self.hits += 1
            return found

    def clear(self) -> None:
        """Forget every value and reset the counters."""
        with self._lock:
            self._entries.clear()
            self.hits = self.misses = 0


class LruFront(Generic[V]):
    """Base of a domain cache that keeps its values in one :class:`SharedLru` (``_lru``) and
    answers in its own terms: the size and the counters are the LRU's."""

    _lru: SharedLru[V]

    @property
    def hits(self) -> int:
        """Answers found in memory."""
        return self._lru.hits

    @property
    def misses(self) -> int:
        """Answers computed afresh."""
        return self._lru.misses

    def __len__(self) -> int:
        return len(self._lru)

    def clear(self) -> None:
        """Forget every value and reset the counters."""
        self._lru.clear()
