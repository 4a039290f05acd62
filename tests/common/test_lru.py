"""The byte-bounded LRU cache the optimizer and the controller share: bounded by bytes, counting
hits, and its storing part (lookup / put) for values computed by a coroutine."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.lru import ENTRY_OVERHEAD, LruCache, array_nbytes


def test_array_bytes_count_every_array_once():
    a = np.zeros(10)
    b = np.zeros((2, 3), dtype=np.int32)
    assert array_nbytes(a, (a, [b]), "text", 3) == a.nbytes + b.nbytes


def test_the_lru_is_bounded_by_bytes_and_counts_hits():
    cache = LruCache[np.ndarray](max_bytes=3 * (800 + ENTRY_OVERHEAD))
    calls = []

    def zeros(n: int):
        def compute() -> np.ndarray:
            calls.append(n)
            return np.zeros(n // 8)

        return compute

    for key in "abc":
        cache.get(key, zeros(800))
    assert cache.get("a", zeros(800)) is cache.get("a", zeros(800))  # a is now the most recent
    cache.get("d", zeros(800))  # b, the least recently used, goes
    assert (cache.hits, cache.misses, len(cache)) == (2, 4, 3)
    assert cache.nbytes == 3 * (800 + ENTRY_OVERHEAD) <= cache.max_bytes
    cache.get("b", zeros(800))
    assert calls == [800, 800, 800, 800, 800]  # b computed again
    big = cache.get("e", zeros(8000))  # heavier than the whole budget: answered, not kept
    assert big.shape == (1000,)
    assert "e" not in cache._entries
    assert cache.nbytes <= cache.max_bytes
    cache.clear()
    assert (cache.hits, cache.misses, len(cache), cache.nbytes) == (0, 0, 0, 0)


def test_values_without_arrays_are_bounded_too():
    cache = LruCache[None](max_bytes=10 * ENTRY_OVERHEAD)
    for key in range(100):
        cache.get(key, lambda: None)
    assert len(cache) == 10
    assert cache.get(99, lambda: None) is None
    assert cache.hits == 1
    with pytest.raises(ValueError, match="max_bytes"):
        LruCache[None](max_bytes=-1)


def test_lookup_and_put_store_and_evict_as_get_does():
    cache = LruCache[bytes](max_bytes=2 * (100 + ENTRY_OVERHEAD), weigh=len)
    assert cache.lookup("a") is None
    assert cache.put("a", b"a" * 100)
    assert cache.put("b", b"b" * 100)
    assert cache.lookup("a") == b"a" * 100  # a is now the most recent
    assert cache.put("c", b"c" * 100)  # b, the least recently used, goes
    assert cache.lookup("b") is None
    assert (cache.hits, cache.misses, len(cache)) == (1, 2, 2)
    assert cache.put("a", b"A" * 50)  # replaced: its old weight is given back
    assert cache.nbytes == 50 + 100 + 2 * ENTRY_OVERHEAD
    assert not cache.put("big", b"x" * 1000)  # heavier than the whole budget: not kept
    assert cache.lookup("big") is None
    assert cache.lookup("a") == b"A" * 50
    assert cache.lookup("c") == b"c" * 100  # nothing was evicted for it
