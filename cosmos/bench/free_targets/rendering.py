"""What draws free targets renders through: the renderer's three routes, over HTTP
(:class:`~services.renderer.client.RendererClient`) or in this process (:class:`LocalRenderer`)."""

from __future__ import annotations

from types import TracebackType
from typing import Protocol, Self

from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.renderer.depth import DepthImage
from services.renderer.engine import RenderEngine
from services.renderer.imaging import encode_png
from services.renderer.settings import RendererSettings
from services.renderer.view import resolve_view
from services.renderer.wiring import build_renderer

__all__ = ["LocalRenderer", "Renderer"]


class Renderer(Protocol):
    """``POST /render``, ``/render/annotations`` and ``/render/depth``, as
    :class:`RendererClient` has them."""

    def render_png(self, request: RenderRequest) -> bytes:
        """The view's PNG bytes."""
        ...

    def annotations(self, request: RenderRequest) -> RenderAnnotations:
        """The view's ground truth."""
        ...

    def depth(self, request: RenderRequest) -> DepthImage:
        """The view's depth and object ids (``POST /render/depth``)."""
        ...


class LocalRenderer:
    """The renderer's routes in this process: the same validation (:func:`resolve_view`, so a
    bad camera raises the same 422 :class:`~services.common.errors.UnprocessableError`) and the
    same engine, on its own worker thread; use it as a context manager. A given ``engine`` is
    the caller's to start and close."""

    def __init__(
        self,
        catalog: SceneCatalog | None = None,
        settings: RendererSettings | None = None,
        engine: RenderEngine | None = None,
    ) -> None:
        self._settings = settings or RendererSettings()
        self._catalog = catalog or SceneCatalog(self._settings.scene_directories())
        self._own = engine is None
        self._engine = engine or build_renderer(self._settings).engine

    def __enter__(self) -> Self:
        if self._own:
            self._engine.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._own:
            self._engine.close()

    def render_png(self, request: RenderRequest) -> bytes:
        view = resolve_view(self._catalog, self._settings, request)
        image = self._engine.render(
            view.scene, view.pose, view.width, view.height, view.spp, view.seed
        )
        return encode_png(image.rgb)

    def annotations(self, request: RenderRequest) -> RenderAnnotations:
        view = resolve_view(self._catalog, self._settings, request)
        return self._engine.annotate(view.scene, view.pose, view.width, view.height, None)

    def depth(self, request: RenderRequest) -> DepthImage:
        view = resolve_view(self._catalog, self._settings, request)
        return self._engine.depth(view.scene, view.pose, view.width, view.height)
