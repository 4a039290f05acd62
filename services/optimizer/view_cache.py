"""A bounded, thread-safe cache of the exact mappings of views, keyed by what they depend on.

The optimizer is stateless over HTTP: every request carries the search's whole history, so a
search's k-th request would map all k views again although only the last one is new. A view's
exact mapping (:func:`.mapping.map_exact`) depends only on its boxes, their classes, the camera
and the pose, so those — by value, not by object identity — are the key, and the cached answer
is exactly the one a fresh mapping would give. The observation enters the key as its
:attr:`~.observations.Observation.digest` (of its classes, boxes, colours and confidences),
which an observation computes once: a search's requests find their views' observations again
(:mod:`.image_cache`), so a lookup costs a dictionary access, not the key's arrays.
"""

from __future__ import annotations

import operator
from dataclasses import fields
from typing import Final

import numpy as np

from services.common.caches import LruFront, SharedLru
from services.common.geometry.scene import CameraSpec
from services.optimizer.mapping import MappedObjects, map_exact
from services.optimizer.observations import Observation

__all__ = ["DEFAULT_VIEW_MAPPINGS", "SHARED_MAPPINGS", "ViewMappings"]

_CAMERA_FIELDS: Final = operator.attrgetter(*CameraSpec.model_fields)

DEFAULT_VIEW_MAPPINGS: Final = 4096
"""Views kept: a search sends a few dozen at most, so this serves ~100 concurrent searches
(a few kB each)."""


class ViewMappings(LruFront[MappedObjects]):
    """LRU of :func:`.mapping.map_exact` results per (observation digest, pose, camera), at most
    ``maxsize`` of them (a :class:`~services.common.caches.SharedLru`; 0 keeps none).

    The arrays handed out are read-only: they are shared by every caller that asks for the
    same view.
    """

    def __init__(self, maxsize: int = DEFAULT_VIEW_MAPPINGS) -> None:
        self._lru = SharedLru[MappedObjects](maxsize)  # raises for a negative maxsize

    @property
    def maxsize(self) -> int:
        return self._lru.maxsize

    def get(
        self, observation: Observation, theta_deg: float, phi_deg: float, camera: CameraSpec
    ) -> MappedObjects:
        """The exact mapping of ``observation`` seen from (θ, φ) in degrees, cached."""
        # The digest covers the kinds too: in identity mode they come from the classes. The
        # camera's values, not the model: a pydantic model hashes and compares in Python.
        key = (observation.digest, float(theta_deg), float(phi_deg), _CAMERA_FIELDS(camera))

        def mapping() -> MappedObjects:
            boxes = np.ascontiguousarray(observation.boxes, dtype=np.float64)
            mapped = map_exact(boxes, observation.kinds, camera, theta_deg, phi_deg)
            for field in fields(mapped):
                getattr(mapped, field.name).flags.writeable = False
            return mapped

        return self._lru.get(key, mapping)


SHARED_MAPPINGS: Final = ViewMappings()
"""The cache of callers that bring none (the simulator, direct strategy calls)."""
