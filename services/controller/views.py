"""Rendered views for the page: a search's target, the view of any of its iterations, any grid pose.

A search records each iteration's pose and detections, not its image. The image of iteration
``i`` is the renderer's answer for the search's scene at ``iterations[i].pose`` with the search's
view settings (samples per pixel, film width: ``Search.view_settings``, recorded when it was
submitted) and the renderer's fixed seed, so it is the same pixels whenever it is asked for,
whatever the controller's settings are by then: :class:`ViewStore` keeps the views rendered
lately (:meth:`ViewStore.remember`, fed by :class:`~services.controller.stages.Stages`), keyed
by scene, pose and settings, up to a number of bytes, and renders the others again. Browsers do
not show binary PPM: views are answered as PNG.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import cv2
import numpy as np

from services.common.caches import LruFront, SharedLru
from services.common.contracts.search import Search, ViewSettings
from services.common.geometry.pose import GridIndex
from services.common.images import decode_image, media_type_of

__all__ = [
    "Render",
    "UnknownIteration",
    "ViewStore",
    "displayable",
    "iteration_pose",
    "to_png",
]

Render = Callable[[str, GridIndex, ViewSettings], Awaitable[bytes]]
"""Renders a view as a search does: the scene, the grid pose, the settings; any image format."""

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


class ViewStore(LruFront[bytes]):
    """PNG views of grid poses, the most recently used kept in memory up to ``max_bytes``.

    A view is keyed by its scene, grid pose and :class:`ViewSettings` (two searches of one pose
    with other settings saw other pixels). ``render(scene, index, settings)`` renders a view as
    a search does; a view the searches rendered is handed in by :meth:`remember` and is not
    rendered again. The settings given are those the view is rendered with, never None: a
    search's own, or the controller's current ones
    (:meth:`~services.controller.stages.Stages.settings_for`).

    Storing and eviction are a byte-bounded :class:`~services.common.caches.SharedLru`'s
    (``lookup`` / ``put``, each view weighed by its length); a render is awaited between them,
    so two requests for one view not kept may both render it (the same pixels).
    """

    def __init__(self, render: Render, max_bytes: int) -> None:
        self._render = render
        self._lru = SharedLru[bytes](max_bytes, weigh=len)
        self.renders = 0

    @property
    def max_bytes(self) -> int:
        """The most bytes of views kept (each counts its length and a small overhead)."""
        return self._lru.maxsize

    @property
    def nbytes(self) -> int:
        """Bytes of views kept now."""
        return self._lru.currsize

    def remember(self, scene: str, index: GridIndex, settings: ViewSettings, image: bytes) -> None:
        """Keep ``image``, the view of ``scene`` at ``index`` as a search rendered it with
        ``settings``."""
        self._lru.put(_key(scene, index, settings), image)

    async def png(self, scene: str, index: GridIndex, settings: ViewSettings) -> bytes:
        """The view of ``scene`` at grid pose ``index`` rendered with ``settings``, as PNG: kept,
        else rendered (the renderer's refusals and the broker's errors pass through)."""
        key = _key(scene, index, settings)
        image = self._lru.lookup(key)
        rendered = image is None
        if image is None:
            image = await self._render(scene, index, settings)
            self.renders += 1
        png = image if image.startswith(_PNG) else await asyncio.to_thread(to_png, image)
        if rendered or png is not image:
            self._lru.put(key, png)  # smaller than the PPM, and not encoded twice
        return png


def _key(
    scene: str, index: GridIndex, settings: ViewSettings
) -> tuple[str, int, int, int | None, int | None]:
    return (scene, index.lat, index.lon, settings.spp, settings.width)
