"""The optimizer service: ``create_app(settings)`` builds it; ``app`` is the default instance.

Run it with ``uvicorn services.optimizer.app:app --port 8003``.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from services.common.http import service_app
from services.common.settings import from_environment
from services.optimizer.api import OptimizerState, router
from services.optimizer.free.target_maps import TargetMapCache
from services.optimizer.refine_pose import ImageLimits
from services.optimizer.settings import OptimizerSettings
from services.optimizer.wiring import build_optimizer

__all__ = ["app", "create_app"]


def create_app(settings: OptimizerSettings | None = None) -> FastAPI:
    """An optimizer app; reads ``COSMOS_*`` settings from the environment unless given
    (and then warns of each ``COSMOS_`` variable that no service reads)."""
    settings = settings or from_environment(OptimizerSettings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.optimizer = OptimizerState(
            context=await asyncio.to_thread(build_optimizer, settings),
            image_limits=ImageLimits(
                settings.optimizer_max_image_pixels, settings.optimizer_max_image_side
            ),
            target_maps=TargetMapCache(settings.optimizer_target_cache_bytes),
        )
        yield

    return service_app(
        "optimizer",
        "Maps detections to the ground and proposes the next camera pose of a search.",
        lifespan,
        router,
        settings.body_limits(),
        settings=settings,
        guarded=True,
        # Ready once started: the calibrations and the catalog, all it needs, are loaded by
        # then, and it keeps no state between requests.
        readiness=None,
    )


app = create_app()
