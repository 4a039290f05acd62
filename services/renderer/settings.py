"""Renderer settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field
from pydantic_settings import BaseSettings

from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.settings import settings_config, split_paths
from services.renderer.variant import VariantRequest

__all__ = ["RendererSettings"]


class RendererSettings(BaseSettings):
    """``COSMOS_SCENES_DIR`` adds scene directories (os.pathsep-separated, searched before the
    built-in ``scenes/``); the rest bound what one request may ask for."""

    model_config = settings_config()

    scenes_dir: str = ""
    mitsuba_variant: VariantRequest = "auto"
    render_spp: Annotated[int, Field(ge=1, le=4096)] = 16
    render_max_spp: Annotated[int, Field(ge=1, le=4096)] = 256
    render_max_side: Annotated[int, Field(ge=16, le=8192)] = 2048
    render_max_pixels: Annotated[int, Field(ge=256)] = 4_194_304
    render_max_samples: Annotated[int, Field(ge=1024)] = 2**26
    render_max_queue: Annotated[int, Field(ge=1, le=10_000)] = 32
    render_scene_cache: Annotated[int, Field(ge=1, le=256)] = 8
    max_body_bytes: Annotated[int, Field(ge=1024)] = 64 * 1024

    def scene_directories(self) -> list[Path]:
        """The directories searched for scene files, in order."""
        return [*split_paths(self.scenes_dir), BUILTIN_SCENES_DIR]
