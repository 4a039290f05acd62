"""Rendered views for the page: a search's target, the view of any of its iterations, any grid pose.

A search records each iteration's pose and detections, not its image. The image of iteration
``i`` is the renderer's answer for the search's scene at ``iterations[i].pose`` with the
controller's view settings (samples per pixel, film width) and the renderer's fixed seed, so it
is the same pixels whenever it is asked for: :class:`ViewStore` keeps the views the searches
rendered lately (:meth:`ViewStore.remember`, fed by :class:`~services.controller.stages.Stages`)
and renders the others again. Browsers do not show binary PPM: views are answered as PNG.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from collections.abc import Awaitable, Callable

import cv2
import numpy as np

from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex
from services.common.images import decode_image, media_type_of

__all__ = ["UnknownIteration", "ViewStore", "displayable", "iteration_pose"]

_PNG = b"\x89PNG\r\n\x1a\n"
_MAX_PIXELS = 8192 * 8192  # what a stored target or a renderer's answer can be at most
_MAX_SIDE = 8192


class UnknownIteration(LookupError):
    """A search has no iteration of that index (yet)."""


def to_png(image: bytes) -> bytes:
    """PNG bytes of a PNG, JPEG or binary PPM image (a PNG is returned as it is)."""
    if image.startswith(_PNG):
        return image
    rgb = decode_image(image, max_pixels=_MAX_PIXELS, max_side=_MAX_SIDE)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("the image could not be encoded as PNG")
    return bytes(png)


def displayable(image: bytes) -> tuple[bytes, str]:
    """``image`` as a browser shows it, and its media type: PNG and JPEG as they are, binary PPM
    as PNG."""
    media_type = media_type_of(image)
    if media_type in {"image/png", "image/jpeg"}:
        return image, media_type
    return to_png(image), "image/png"


def iteration_pose(search: Search, index: int) -> GridIndex:
    """The grid pose of ``search``'s iteration ``index``; :class:`UnknownIteration` if it has
    none (yet)."""
    if not 0 <= index < len(search.iterations):
        raise UnknownIteration(
            f"search {search.id} has {len(search.iterations)} recorded iterations; "
            f"there is no iteration {index}"
        )
    return search.iterations[index].pose.index


class ViewStore:
    """PNG views of grid poses, the ``capacity`` most recently used kept in memory.

    ``render(scene, index)`` renders a view as a search does (any image format); a view the
    searches rendered is handed in by :meth:`remember` and is not rendered again.
    """

    def __init__(
        self, render: Callable[[str, GridIndex], Awaitable[bytes]], capacity: int = 64
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self._render = render
        self.capacity = capacity
        self.hits = 0
        self.renders = 0
        self._views: OrderedDict[tuple[str, int, int], bytes] = OrderedDict()

    def __len__(self) -> int:
        return len(self._views)

    def remember(self, scene: str, index: GridIndex, image: bytes) -> None:
        """Keep ``image``, the view of ``scene`` at ``index`` as a search rendered it."""
        self._keep((scene, index.lat, index.lon), image)

    def _keep(self, key: tuple[str, int, int], image: bytes) -> None:
        self._views[key] = image
        self._views.move_to_end(key)
        while len(self._views) > self.capacity:
            self._views.popitem(last=False)

    async def png(self, scene: str, index: GridIndex) -> bytes:
        """The view of ``scene`` at grid pose ``index`` as PNG: kept, else rendered (the
        renderer's refusals and the broker's errors pass through)."""
        key = (scene, index.lat, index.lon)
        image = self._views.get(key)
        if image is None:
            image = await self._render(scene, index)
            self.renders += 1
        else:
            self.hits += 1
        png = image if image.startswith(_PNG) else await asyncio.to_thread(to_png, image)
        self._keep(key, png)  # smaller than the PPM, and not encoded twice
        return png
