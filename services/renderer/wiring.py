"""The renderer's composition root: :func:`build_renderer`, used by its app and the bench alike,
so that what the service is made of is wired once."""

from __future__ import annotations

from services.common.catalog import SceneCatalog
from services.renderer.api import RendererState
from services.renderer.engine import RenderEngine
from services.renderer.settings import RendererSettings

__all__ = ["build_renderer"]


def build_renderer(settings: RendererSettings) -> RendererState:
    """The renderer's parts, wired once: its scene catalog (read from disk) and its engine (not
    started: :meth:`RenderEngine.start` loads Mitsuba on the render thread)."""
    catalog = SceneCatalog(settings.scene_directories())
    engine = RenderEngine(
        settings.renderer_mitsuba_variant,
        settings.renderer_scene_cache,
        settings.renderer_max_queue,
        slice_samples=settings.renderer_slice_samples,
    )
    return RendererState(settings=settings, catalog=catalog, engine=engine)
