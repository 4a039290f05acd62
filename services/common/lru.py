"""A thread-safe LRU cache bounded by the bytes it holds, counting its hits and misses.

``functools.lru_cache`` bounds the number of entries only, but what is cached here varies in
size: the optimizer's derived arrays grow with the grid and the detections (one view predicted
into every pose of a 25,000-pose grid weighs megabytes), the controller's views with their film.
So a count says little about memory. Here every value is weighed when stored (``weigh``:
:func:`array_nbytes` by default, ``len`` for bytes; plus :data:`ENTRY_OVERHEAD` for the key and
the bookkeeping), the least recently used entries go until the total fits ``max_bytes``, and a
value heavier than that is returned but not kept.

:meth:`LruCache.get` computes a missing value synchronously; a caller whose values come from a
coroutine uses :meth:`LruCache.lookup` and :meth:`LruCache.put` around its ``await`` instead.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Final, Generic, TypeVar

import numpy as np

__all__ = ["ENTRY_OVERHEAD", "LruCache", "array_nbytes"]

V = TypeVar("V")

ENTRY_OVERHEAD: Final = 256
"""Bytes an entry counts besides its arrays, so that array-free values are bounded too."""


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


class LruCache(Generic[V]):
    """Values by key, least recently used first out, at most ``max_bytes`` of them by ``weigh``.

    Values are shared by every caller that asks for the same key: nobody may change them.
    """

    def __init__(self, max_bytes: int, weigh: Callable[[V], int] = array_nbytes) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self.hits = 0
        self.misses = 0
        self._weigh = weigh
        self._entries: OrderedDict[Hashable, tuple[V, int]] = OrderedDict()
        self._nbytes = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def nbytes(self) -> int:
        """Bytes held now (never more than ``max_bytes``)."""
        return self._nbytes

    def lookup(self, key: Hashable) -> V | None:
        """The stored value of ``key`` (now the most recently used), else None; counted as a
        hit or a miss. (A cache whose values may be None tells them apart with :meth:`get`.)"""
        found = self._find(key)
        return None if found is None else found[0]

    def get(self, key: Hashable, compute: Callable[[], V]) -> V:
        """The value of ``key``: the stored one, else ``compute()`` (stored when it fits)."""
        found = self._find(key)
        if found is not None:
            return found[0]
        # Computed outside the lock: two threads may compute one value at once, never wait.
        value = compute()
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: V) -> bool:
        """Store ``value`` as ``key``'s (replacing any), the least recently used entries going
        until the total fits; False (and nothing stored) when it alone weighs more than
        ``max_bytes``."""
        size = self._weigh(value) + ENTRY_OVERHEAD
        if size > self.max_bytes:
            return False
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._nbytes -= old[1]
            self._entries[key] = (value, size)
            self._nbytes += size
            while self._nbytes > self.max_bytes:
                _, (_, dropped) = self._entries.popitem(last=False)
                self._nbytes -= dropped
        return True

    def _find(self, key: Hashable) -> tuple[V, int] | None:
        """``key``'s entry, made the most recently used, counting a hit or a miss."""
        with self._lock:
            found = self._entries.get(key)
            if found is None:
                self.misses += 1
                return None
            self._entries.move_to_end(key)
            self.hits += 1
            return found

    def clear(self) -> None:
        """Forget every value and reset the counters."""
        with self._lock:
            self._entries.clear()
            self._nbytes = 0
            self.hits = self.misses = 0
