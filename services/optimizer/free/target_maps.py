"""The target's side of the dense refinement, made once per search: its grey image on the
render's film and its pyramid of oriented distance maps (:func:`~.edges.target_level`).

A free search refines against the same target after every render it makes (a refit at the
fitted pose, a candidate's dense fit, its rivals), and each ``/refine-pose`` request carries the
target again. What the fit needs of it depends only on the image's bytes and the film it is
brought to, so those are the key (a BLAKE2b digest of the bytes: about 1 ms a megabyte).
Measured by ``python -m benchmarks.target_maps`` (one run, the intrinsics given): a later
render's refinement took 27 → 17 ms with a 320 x 240 PNG target, and 100 → 36 ms with a
4000 x 3000 JPEG (a drone's photo) refined on a 640 x 480 render, its decoding kept too.
``POST /refine-pose/target`` makes them before the first refinement (the controller asks while
the search's first view is rendered), so that one finds them too.

A :class:`TargetMapCache` bounds the maps by bytes (:class:`~services.common.caches.SharedLru`:
a level weighs 96 bytes a pixel of its own, the full-resolution one 7.4 MB at 320 x 240), least
recently used out; a bound of 0 keeps nothing and every request makes its own.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.caches import SharedLru, array_nbytes
from services.common.contracts.optimize import TargetCacheStats
from services.optimizer.free.edges import Level, gray, target_level, with_contrast

__all__ = ["DEFAULT_TARGET_CACHE_BYTES", "TargetMapCache", "TargetMaps"]

DEFAULT_TARGET_CACHE_BYTES: Final = 128 * 2**20
"""Room for every level of twelve searches' targets refined at 320 x 240 (9.7 MB each), three
at 640 x 480 (39 MB)."""

_Key = tuple[bytes, tuple[int, int]]


class TargetMaps:
    """One target's grey image on a film, its contrast raised to :data:`~.edges.MIN_SPAN`
    (:func:`~.edges.with_contrast`), and its distance-map levels, each made when first asked
    for (and kept in ``levels`` under ``key``, when given)."""

    def __init__(
        self,
        target_gray: NDArray[np.uint8],
        levels: SharedLru[Level] | None = None,
        key: _Key | None = None,
    ) -> None:
        self.gray = with_contrast(gray(np.asarray(target_gray, dtype=np.uint8)))
        self._levels = levels if key is not None else None
        self._key = key

    @property
    def shape(self) -> tuple[int, int]:
        """The film's ``(h, w)``."""
        h, w = self.gray.shape
        return h, w

    def kept(self, scale: int, sigma: float, cap: float) -> bool:
        """Whether that level of this target is kept now."""
        return self._levels is not None and (self._key, scale, sigma, cap) in self._levels

    def level(self, scale: int, sigma: float, cap: float) -> Level:
        """:func:`~.edges.target_level` of the grey image, kept when this target is."""
        if self._levels is None or self._key is None:
            return target_level(self.gray, scale, sigma, cap)
        return self._levels.get(
            (self._key, scale, sigma, cap),
            lambda: _frozen(target_level(self.gray, scale, sigma, cap)),
        )


class TargetMapCache:
    """Targets' grey images and distance maps by the image's bytes and film, at most
    ``max_bytes`` of arrays in all (module docstring)."""

    def __init__(self, max_bytes: int = DEFAULT_TARGET_CACHE_BYTES) -> None:
        self.grays = SharedLru[NDArray[np.uint8]](max_bytes // 16, weigh=array_nbytes)
        self.levels = SharedLru[Level](max_bytes - max_bytes // 16, weigh=array_nbytes)

    def stats(self) -> TargetCacheStats:
        """What is kept, and the target lookups that found it or made it."""
        return TargetCacheStats(
            targets=len(self.grays),
            bytes=self.grays.currsize + self.levels.currsize,
            max_bytes=self.grays.maxsize + self.levels.maxsize,
            hits=self.grays.hits,
            misses=self.grays.misses,
        )

    def maps(
        self, data: bytes, film: tuple[int, int], decode: Callable[[], NDArray[np.uint8]]
    ) -> TargetMaps:
        """The maps of the image ``data`` on ``film`` ``(w, h)``; ``decode`` makes its grey
        image there when it is not kept."""
        key = (hashlib.blake2b(data, digest_size=16).digest(), film)
        return TargetMaps(self.grays.get(key, lambda: _frozen_gray(decode())), self.levels, key)


def _frozen_gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """``image``, read-only: every request for its target shares it."""
    image.setflags(write=False)
    return image


def _frozen(level: Level) -> Level:
    """``level`` with its arrays read-only: every request for its target shares them."""
    for array in level.arrays():
        array.setflags(write=False)
    return level
