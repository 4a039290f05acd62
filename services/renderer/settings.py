"""Renderer settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field

from services.common.auth import ServiceTokenSettings
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.settings import split_paths
from services.renderer.scheduler import DEFAULT_SLICE_SAMPLES
from services.renderer.variant import VariantRequest

__all__ = ["RendererSettings"]


class RendererSettings(ServiceTokenSettings):
    """``COSMOS_SCENES_DIR`` adds scene directories (os.pathsep-separated, searched before the
    built-in ``scenes/``); the rest, ``COSMOS_RENDERER_…``, pick the Mitsuba variant and bound
    what one request may ask for."""

    scenes_dir: str = ""
    """Extra scene directories, ``os.pathsep``-separated, searched before the built-in ones."""
    renderer_mitsuba_variant: VariantRequest = "auto"
    """``llvm_ad_rgb``, ``scalar_rgb``, or ``auto``: LLVM when a libLLVM >= 16 is found."""
    renderer_default_spp: Annotated[int, Field(ge=1, le=4096)] = 16
    """Samples per pixel of a request that gives none."""
    renderer_max_spp: Annotated[int, Field(ge=1, le=4096)] = 256
    """The most samples per pixel one request may ask for."""
    renderer_max_side: Annotated[int, Field(ge=16, le=8192)] = 2048
    """The longest film side one request may ask for, in pixels."""
    renderer_max_pixels: Annotated[int, Field(ge=256)] = 4_194_304
    """The most film pixels (width x height) one request may ask for."""
    renderer_max_samples: Annotated[int, Field(ge=1024)] = 2**26
    """The most samples (pixels x spp) one request may cost; more is a 422 naming it."""
    renderer_max_queue: Annotated[int, Field(ge=1, le=10_000)] = 32
    """Renders waiting or running at once; one more gets 503."""
    renderer_slice_samples: Annotated[int, Field(ge=4096)] = DEFAULT_SLICE_SAMPLES
    """Samples per slice of work: a larger render runs as sample passes of at most this many
    (but at least one per pixel), and more urgent requests (search views) go between them."""
    renderer_scene_cache: Annotated[int, Field(ge=1, le=256)] = 8
    """Loaded Mitsuba scenes kept (one per scene and film size)."""
    renderer_max_body_bytes: Annotated[int, Field(ge=1024)] = 64 * 1024
    """Request body limit, in bytes."""

    def scene_directories(self) -> list[Path]:
        """The directories searched for scene files, in order."""
        return [*split_paths(self.scenes_dir), BUILTIN_SCENES_DIR]
