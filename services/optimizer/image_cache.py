"""A bounded, thread-safe cache of what planning makes of each image of a request on its own,
keyed by the image's content.

The optimizer is stateless over HTTP: every ``/next-pose`` request carries the search's whole
history, so its k-th request would check, scale and deduplicate all k views again although only
the last one is new (≈ 90 µs a view, 3.6 ms at 40 views of a simulated demo search). What
planning derives from one image — its boxes checked against the image and the camera, its
pose found on the grid, its detections in camera pixels with second boxes on one object
dropped (:func:`~.observations.merge_duplicates`) — depends only on the image's detections
and pose and on the request's camera, grid and object classes, so those, by value, are the key:
a search's earlier views are found again whichever request brings them, and a restarted
optimizer only computes them once more. An image that fails a check raises and is not stored.
"""

from __future__ import annotations

import functools
import math
import operator
import sys
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from typing import Final

from services.common.caches import LruFront, SharedLru, array_nbytes
from services.common.contracts.detect import Detection
from services.common.contracts.optimize import ImageDetections, VisitedView
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.pose import PoseQuery
from services.common.geometry.scene import CameraSpec
from services.optimizer.observations import Observation
from services.optimizer.problem import Visit
from services.optimizer.proxies import ProxyKind

__all__ = ["DEFAULT_IMAGE_CACHE_BYTES", "ImageCache", "SeenImage"]

DEFAULT_IMAGE_CACHE_BYTES: Final = 16 * 2**20
"""About 3.6 kB an image of 5 detections, key included: room for the views of ~100 searches
of 40 views at once."""


_DETECTION_FIELDS: Final = operator.attrgetter(*Detection.model_fields)
_POSE_FIELDS: Final = operator.attrgetter(*PoseQuery.model_fields)


@dataclass(frozen=True)
class SeenImage:
    """One image of a request as planning uses it.

    Attributes
    ----------
    observation : Observation
        The detections in the camera's pixels, second boxes on one object dropped; its arrays
        are read-only (shared by every request that brings the image).
    merged : tuple of str
        One note per dropped box.
    flat, theta_deg, phi_deg
        A visited view's grid pose (flat index) and its angles in degrees; -1 and NaN for the
        target.
    """

    observation: Observation
    merged: tuple[str, ...] = ()
    flat: int = -1
    theta_deg: float = math.nan
    phi_deg: float = math.nan

    @functools.cached_property
    def visit(self) -> Visit:
        """The visited view as the strategies take it."""
        return Visit(self.flat, self.theta_deg, self.phi_deg, self.observation)


def _key_nbytes(node: object) -> int:
    """Bytes of a key of tuples, strings and numbers (shared small objects counted too)."""
    if isinstance(node, tuple):
        return sys.getsizeof(node) + sum(_key_nbytes(item) for item in node)
    return sys.getsizeof(node)


class ImageCache(LruFront[tuple[SeenImage, int]]):
    """LRU of :class:`SeenImage` per (setting, image), at most ``max_bytes`` of them (arrays and
    keys); ``max_bytes=0`` keeps nothing (every image computed afresh)."""

    def __init__(self, max_bytes: int = DEFAULT_IMAGE_CACHE_BYTES) -> None:
        self._lru = SharedLru[tuple[SeenImage, int]](max_bytes, weigh=lambda entry: entry[1])

    @property
    def nbytes(self) -> int:
        """Bytes held now (keys and arrays, estimated, plus the LRU's overhead per entry)."""
        return self._lru.currsize

    @property
    def max_bytes(self) -> int:
        return self._lru.maxsize

    @staticmethod
    def setting(
        camera: CameraSpec, grid: HemisphereGrid, classes: Mapping[str, ProxyKind] | None
    ) -> str:
        """What besides the image a :class:`SeenImage` depends on, as one exact string (made
        once per request; a string keeps its hash, so the images' keys hash fast)."""
        kinds = None if classes is None else sorted((label, int(k)) for label, k in classes.items())
        return repr((camera, grid, kinds))

    def get(
        self, setting: str, image: ImageDetections, compute: Callable[[], SeenImage]
    ) -> SeenImage:
        """The :class:`SeenImage` of ``image`` under ``setting``: the stored one, else
        ``compute()`` (which raises for an image that fails a check; nothing is then stored).

        The key holds every field of the image (and a visited view's pose) by value, numbers
        compared as Python compares them (``-0.0 == 0.0``).
        """
        key: Hashable = (
            setting,
            _POSE_FIELDS(image.pose) if isinstance(image, VisitedView) else None,
            image.image_size,
            tuple(map(_DETECTION_FIELDS, image.detections)),
        )

        def stored() -> tuple[SeenImage, int]:
            seen = compute()
            observation = seen.observation
            for array in (observation.boxes, observation.colors, observation.confidence):
                array.flags.writeable = False
            return seen, _key_nbytes(key) + array_nbytes(seen)

        return self._lru.get(key, stored)[0]
