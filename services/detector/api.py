"""Detector routes: thin HTTP wrappers over :class:`~services.detector.registry.ModelRegistry`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response

from services.common.contracts.detect import (
    DetectorHealth,
    DetectorModels,
    DetectResponse,
    ModelInfo,
)
from services.common.geometry.scene import SCENE_ID_PATTERN
from services.common.http import app_state, problem_responses
from services.common.upload import read_upload, request_body
from services.detector.registry import ModelRegistry
from services.detector.settings import DetectorSettings

__all__ = ["DetectorState", "router"]

router = APIRouter()


@dataclass(frozen=True)
class DetectorState:
    """What the routes need, built in the app's lifespan."""

    settings: DetectorSettings
    registry: ModelRegistry


State = Annotated[DetectorState, Depends(app_state("detector"))]


@router.get("/health", response_model=DetectorHealth)
async def health(state: State) -> DetectorHealth:
    """Liveness, the general model, requests in flight (all models), the general model's
    inference set-up and batches, how many scenes' own models serve, and the bytes of decoded
    images held (now, at most, and the budget)."""
    detector = state.registry.general
    budget = detector.admission.decode
    return DetectorHealth(
        status="ok",
        service="detector",
        model=detector.info.name,
        model_sha256=detector.info.sha256,
        in_flight=detector.in_flight,
        providers=detector.model.providers,
        intra_op_threads=detector.model.threads,
        max_batch=detector.batcher.max_batch,
        batches_run=detector.batcher.stats.batches,
        images_run=detector.batcher.stats.images,
        scene_models=state.registry.serving(),
        decode_bytes=budget.in_use,
        decode_bytes_peak=budget.peak,
        max_decode_bytes=budget.limit_bytes,
    )


@router.get("/model", response_model=ModelInfo)
async def model(state: State) -> ModelInfo:
    """The general model: name, classes, input size (width, height), file SHA-256 and
    provenance."""
    return state.registry.general.info


@router.get("/models", response_model=DetectorModels)
async def models(state: State) -> DetectorModels:
    """The general model and every scene's own model: `serving`, `refused` (with the error; the
    scene's previous model, if any, goes on serving) or `none`. Looks for new model files first."""
    return await state.registry.models()


@router.post(
    "/detect",
    response_model=DetectResponse,
    responses=problem_responses(400, 413, 415, 422, 503),
    openapi_extra={"requestBody": request_body()},
)
async def detect(
    request: Request,
    state: State,
    conf: Annotated[
        float | None,
        Query(
            ge=0.0,
            le=1.0,
            allow_inf_nan=False,
            description="Confidence threshold for this request (default: the service's).",
        ),
    ] = None,
    max_detections: Annotated[
        int | None,
        Query(ge=1, le=1000, description="At most this many detections, best first."),
    ] = None,
    scene: Annotated[
        str | None,
        Query(
            pattern=SCENE_ID_PATTERN,
            description="The scene the image shows: its own model detects (labels are its "
            "objects' names) when it has a valid one; an unknown scene, or one without a valid "
            "model, gets the general model (labels are shapes). The answer's `model.scene` "
            "says which served.",
        ),
    ] = None,
) -> Response:
    """Detect the objects in an image (multipart field ``image``, or the raw image body): per
    object its class, confidence, box in pixels of the uploaded image and mean colour. With
    ``scene``, that scene's own model detects if it has a valid one, else the general model."""
    data = (await read_upload(request)).image
    found = await state.registry.detect(data, scene=scene, conf=conf, max_detections=max_detections)
    # Serialised once by pydantic-core; returning the model would validate it again first.
    return Response(found.model_dump_json(), media_type="application/json")
