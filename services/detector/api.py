"""Detector routes: thin HTTP wrappers over :class:`~services.detector.detect.Detector`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response

from services.common.http import app_state, problem_responses
from services.common.models import DetectorHealth, DetectResponse, ModelInfo
from services.common.upload import read_upload, request_body
from services.detector.detect import Detector
from services.detector.settings import DetectorSettings

__all__ = ["DetectorState", "router"]

router = APIRouter()


@dataclass(frozen=True)
class DetectorState:
    """What the routes need, built in the app's lifespan."""

    settings: DetectorSettings
    detector: Detector


State = Annotated[DetectorState, Depends(app_state("detector"))]


@router.get("/health", response_model=DetectorHealth)
async def health(state: State) -> DetectorHealth:
    """Liveness, the model being served, requests in flight and the inference set-up."""
    detector = state.detector
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
    )


@router.get("/model", response_model=ModelInfo)
async def model(state: State) -> ModelInfo:
    """The model: name, classes, input size (width, height), file SHA-256 and provenance."""
    return state.detector.info


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
) -> Response:
    """Detect the objects in an image (multipart field ``image``, or the raw image body): per
    object its class, confidence, box in pixels of the uploaded image and mean colour."""
    data = (await read_upload(request)).image
    found = await state.detector.detect(data, conf=conf, max_detections=max_detections)
    # Serialised once by pydantic-core; returning the model would validate it again first.
    return Response(found.model_dump_json(), media_type="application/json")
