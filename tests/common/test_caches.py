"""The shared LRU over cachetools: bounded by entries or by bytes, counting hits, computing a
missing value once per miss, and safe to share between threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from services.common.caches import ENTRY_OVERHEAD, SharedLru, array_nbytes


def test_array_bytes_count_every_array_once():
    a = np.zeros(10)
    b = np.zeros((2, 3), dtype=np.int32)
    assert array_nbytes(a, (a, [b]), "text", 3) == a.nbytes + b.nbytes


def test_the_lru_is_bounded_by_bytes_and_counts_hits():
    cache = SharedLru[np.ndarray](3 * (800 + ENTRY_OVERHEAD), weigh=array_nbytes)
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
    assert cache.currsize == 3 * (800 + ENTRY_OVERHEAD) <= cache.maxsize
    cache.get("b", zeros(800))
    assert calls == [800, 800, 800, 800, 800]  # b computed again
    big = cache.get("e", zeros(8000))  # heavier than the whole budget: answered, not kept
    assert big.shape == (1000,)
    assert "e" not in cache
    assert cache.currsize <= cache.maxsize
    cache.clear()
    assert (cache.hits, cache.misses, len(cache), cache.currsize) == (0, 0, 0, 0)


def test_values_without_arrays_are_bounded_too():
    cache = SharedLru[None](10 * ENTRY_OVERHEAD, weigh=array_nbytes)
    for key in range(100):
        cache.get(key, lambda: None)
    assert len(cache) == 10
    assert cache.get(99, lambda: None) is None
    assert cache.hits == 1
    with pytest.raises(ValueError, match="maxsize"):
        SharedLru[None](-1)


def test_lookup_and_put_store_and_evict_as_get_does():
    cache = SharedLru[bytes](2 * (100 + ENTRY_OVERHEAD), weigh=len)
    assert cache.lookup("a") is None
    assert cache.put("a", b"a" * 100)
    assert cache.put("b", b"b" * 100)
    assert cache.lookup("a") == b"a" * 100  # a is now the most recent
    assert cache.put("c", b"c" * 100)  # b, the least recently used, goes
    assert cache.lookup("b") is None
    assert (cache.hits, cache.misses, len(cache)) == (1, 2, 2)
    assert cache.put("a", b"A" * 50)  # replaced: its old weight is given back
    assert cache.currsize == 50 + 100 + 2 * ENTRY_OVERHEAD
    assert not cache.put("big", b"x" * 1000)  # heavier than the whole budget: not kept
    assert cache.lookup("big") is None
    assert cache.lookup("a") == b"A" * 50
    assert cache.lookup("c") == b"c" * 100  # nothing was evicted for it


def test_a_count_bound_keeps_the_most_recently_used_entries():
    cache = SharedLru[str](2)
    for key in "aba":
        cache.get(key, key.upper)
    cache.get("c", lambda: "C")  # b, the least recently used, goes
    assert cache.keys() == ("a", "c")
    assert (cache.hits, cache.misses) == (1, 3)
    nothing = SharedLru[str](0)  # keeps nothing: every value is computed again
    assert nothing.get("a", lambda: "A") == nothing.get("a", lambda: "A") == "A"
    assert (len(nothing), nothing.hits, nothing.misses) == (0, 0, 2)


def test_threads_share_the_cache_safely():
    cache = SharedLru[int](3)

    def work(i: int) -> bool:
        k = i % 5
        return cache.get(k, lambda: k * k) == k * k

    with ThreadPoolExecutor(max_workers=4) as pool:
        assert all(pool.map(work, range(400)))
    assert len(cache) <= 3
    assert cache.hits + cache.misses == 400
