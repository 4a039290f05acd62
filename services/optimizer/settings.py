"""Optimizer settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field

from services.common import DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_UPLOAD_BYTES
from services.common.auth import ServiceTokenSettings
from services.common.bodies import BodyLimits
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.contracts.optimize import StrategyName
from services.common.settings import split_paths
from services.optimizer.calibration import DEFAULT_CALIBRATION_FILE
from services.optimizer.free.target_maps import DEFAULT_TARGET_CACHE_BYTES

__all__ = ["OptimizerSettings"]


class OptimizerSettings(ServiceTokenSettings):
    """``COSMOS_OPTIMIZER_DEFAULT_STRATEGY`` picks the strategy of requests that name none;
    ``COSMOS_OPTIMIZER_PAPER_CALIBRATION`` is the JSON file of the paper mapping's coefficients;
    ``COSMOS_SCENES_DIR`` adds scene directories for requests that name a ``scene``
    (as for the renderer); the rest bound what one request may ask for."""

    optimizer_default_strategy: StrategyName = "reprojection"
    """The strategy of a request that names none."""
    optimizer_paper_calibration: Path = DEFAULT_CALIBRATION_FILE
    """The paper mapping's fitted coefficients (``python -m tools.fit_paper_mapping``)."""
    scenes_dir: str = ""
    """Extra scene directories (as the renderer's), for requests that name a ``scene``."""
    optimizer_max_grid_poses: Annotated[int, Field(ge=1, le=100_000)] = 25_000
    """The largest grid one request may have scored, in poses."""
    optimizer_max_history_detections: Annotated[int, Field(ge=1, le=1_000_000)] = 4_000
    """Detections of the visited views one request may carry."""
    optimizer_max_body_bytes: Annotated[int, Field(ge=1024)] = (
        DEFAULT_MAX_UPLOAD_BYTES + 16 * 1024 * 1024
    )
    """Request body limit, in bytes: a ``/refine-pose`` form carries the target (the controller
    takes uploads up to 48 MiB) and the render's archive (9 bytes a pixel: 2.8 MB at 640x480).
    Four maximal bodies may be held at once; bodies up to 1/16 of this (every JSON request)
    count in a lane of their own (:mod:`services.common.bodies`)."""
    optimizer_max_image_pixels: Annotated[int, Field(ge=64, le=1 << 28)] = DEFAULT_MAX_IMAGE_PIXELS
    """The largest target image ``/refine-pose`` decodes (width x height, from its header)."""
    optimizer_max_image_side: Annotated[int, Field(ge=8, le=65_535)] = 16_384
    """The longest side of a target image ``/refine-pose`` decodes, in pixels."""
    optimizer_target_cache_bytes: Annotated[int, Field(ge=0)] = DEFAULT_TARGET_CACHE_BYTES
    """Memory for the free searches' targets as ``/refine-pose`` makes them (grey images and
    distance maps, kept between a search's renders; 0 keeps none), in bytes."""

    def body_limits(self) -> BodyLimits:
        """How request bodies are bounded: the size limit, four maximal bodies in flight."""
        return BodyLimits.for_limit(self.optimizer_max_body_bytes)

    def scene_directories(self) -> list[Path]:
        """The directories searched for scene files, in order."""
        return [*split_paths(self.scenes_dir), BUILTIN_SCENES_DIR]
