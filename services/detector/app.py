"""The detector service: ``create_app(settings)`` builds it; ``app`` is the default instance.

Run it with ``python -m services.common.server services.detector.app:app --port 8002``. The
general model (``COSMOS_DETECTOR_MODEL``, default ``models/detector.onnx``) is loaded at
start-up, not at import: a missing or malformed model stops the start-up with a
:class:`~services.detector.model.ModelError` naming the file. The scenes' own models are loaded
then too, but a refused one only is logged (:mod:`services.detector.registry`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from services.common.catalog import SceneCatalog
from services.common.http import service_app
from services.common.settings import from_environment
from services.detector.api import DetectorState, router
from services.detector.detect import Detector
from services.detector.model import DetectorModel
from services.detector.registry import ModelRegistry
from services.detector.settings import DetectorSettings

__all__ = ["app", "build_detector", "create_app"]

_log = logging.getLogger("cosmos.detector")


async def build_detector(settings: DetectorSettings) -> DetectorState:
    """The detector's parts, wired once: the general model (loaded and started: a missing or
    broken one stops the start-up), the scene catalog, and the registry of scene models (not
    started)."""
    model = await asyncio.to_thread(
        DetectorModel, settings.detector_model, threads=settings.detector_threads
    )
    detector = Detector(model, settings)
    await detector.start()
    _log.info(
        "serving %s (%s, input %s, classes %s) on %s",
        model.path,
        model.info.sha256[:12],
        model.info.input_size,
        ", ".join(model.classes),
        ", ".join(model.providers),
    )
    catalog = await asyncio.to_thread(SceneCatalog, settings.scene_directories())
    registry = ModelRegistry(detector, catalog, settings)
    return DetectorState(settings=settings, registry=registry)


def create_app(settings: DetectorSettings | None = None) -> FastAPI:
    """A detector app; reads ``COSMOS_*`` settings from the environment unless given
    (and then warns of each ``COSMOS_`` variable that no service reads)."""
    settings = settings or from_environment(DetectorSettings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = await build_detector(settings)
        try:
            await state.registry.start()
            app.state.detector = state
            yield
        finally:
            await state.registry.close()
            await state.registry.general.close()

    return service_app(
        "detector",
        "Finds the scene's objects in an image: class, box, confidence and colour.",
        lifespan,
        router,
        settings.body_limits(),
        settings=settings,
        guarded=True,
        # Ready once started: the general model, all it needs, is loaded by then (a missing or
        # broken one stops the start-up; a refused scene model leaves the general one serving).
        readiness=None,
    )


app = create_app()
