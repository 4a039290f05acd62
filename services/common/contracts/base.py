"""Moved to :mod:`services.common.base` (below both the contracts and the geometry, so the two
packages no longer import each other); this name stays only for ``services/controller/api.py``
until its restructuring imports :mod:`services.common.base`, then it goes."""

from services.common.base import MAX_SAFE_INTEGER

__all__ = ["MAX_SAFE_INTEGER"]
