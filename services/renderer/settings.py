"""Renderer settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field

from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.settings import ServiceSettings, split_paths
from services.renderer.variant import VariantRequest

__all__ = ["RendererSettings"]


class RendererSettings(ServiceSettings):
    """``COSMOS_SCENES_DIR`` adds scene directories (os.pathsep-separated, searched before the
    built-in ``scenes/``); the rest bound what one request may ask for.

    ``COSMOS_RENDER_SPP`` and ``COSMOS_MAX_BODY_BYTES``, which other services read too, are
    read as ``COSMOS_RENDERER_DEFAULT_SPP`` and ``COSMOS_RENDERER_MAX_BODY_BYTES`` for one more
    release, with a warning."""

    renamed = {
        "COSMOS_RENDER_SPP": "renderer_default_spp",
        "COSMOS_MAX_BODY_BYTES": "renderer_max_body_bytes",
    }

    scenes_dir: str = ""
    mitsuba_variant: VariantRequest = "auto"
    renderer_default_spp: Annotated[int, Field(ge=1, le=4096)] = 16
    """Samples per pixel of a request that gives none."""
    render_max_spp: Annotated[int, Field(ge=1, le=4096)] = 256
    render_max_side: Annotated[int, Field(ge=16, le=8192)] = 2048
    render_max_pixels: Annotated[int, Field(ge=256)] = 4_194_304
    render_max_samples: Annotated[int, Field(ge=1024)] = 2**26
    render_max_queue: Annotated[int, Field(ge=1, le=10_000)] = 32
    render_scene_cache: Annotated[int, Field(ge=1, le=256)] = 8
    renderer_max_body_bytes: Annotated[int, Field(ge=1024)] = 64 * 1024

    def scene_directories(self) -> list[Path]:
        """The directories searched for scene files, in order."""
        return [*split_paths(self.scenes_dir), BUILTIN_SCENES_DIR]
