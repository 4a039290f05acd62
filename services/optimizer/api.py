"""Optimizer routes: thin HTTP wrappers over planning (:mod:`services.optimizer.planning`) and the
free pose (:mod:`services.optimizer.free_pose`)."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Annotated, TypeVar, get_args

from fastapi import APIRouter, Depends, Request, Response
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from services.common import DEFAULT_MAX_IMAGE_PIXELS
from services.common.contracts.free import FreePoseRequest, FreePoseResponse
from services.common.contracts.optimize import (
    MapRequest,
    MapResponse,
    NextPoseRequest,
    NextPoseResponse,
    OptimizerHealth,
    StrategyInfo,
    StrategyName,
)
from services.common.contracts.refine import (
    REFINE_PARTS,
    TARGET_PARTS,
    RefinePoseRequest,
    RefinePoseResponse,
    TargetRequest,
    TargetResponse,
)
from services.common.contracts.start_pose import StartPoseRequest, StartPoseResponse
from services.common.errors import BadRequestError, UnprocessableError, UnsupportedMediaTypeError
from services.common.http import app_state, problem_responses
from services.optimizer.free.target_maps import TargetMapCache
from services.optimizer.free_pose import SceneObjectCache, free_pose
from services.optimizer.json_body import json_request_body, read_json
from services.optimizer.planning import OptimizerContext, map_detections, next_pose
from services.optimizer.refine_pose import ImageLimits, prepare_target, refine_pose
from services.optimizer.start_planning import start_pose
from services.optimizer.strategies import STRATEGIES

__all__ = ["OptimizerState", "router"]

router = APIRouter()
M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True)
class OptimizerState:
    """What the routes need, built in the app's lifespan."""

    context: OptimizerContext
    free_objects: SceneObjectCache = field(default_factory=SceneObjectCache)
    image_limits: ImageLimits = field(
        default_factory=lambda: ImageLimits(DEFAULT_MAX_IMAGE_PIXELS, 16_384)
    )
    target_maps: TargetMapCache = field(default_factory=TargetMapCache)


State = Annotated[OptimizerState, Depends(app_state("optimizer"))]


@router.get("/health", response_model=OptimizerHealth)
async def health(state: State) -> OptimizerHealth:
    """Liveness, the strategies on offer, the stored paper calibrations and what is kept of
    free searches' targets (:meth:`~.free.target_maps.TargetMapCache.stats`)."""
    return OptimizerHealth(
        status="ok",
        service="optimizer",
        strategies=get_args(StrategyName),
        default_strategy=state.context.default_strategy,
        paper_calibrations=len(state.context.calibrations),
        target_cache=state.target_maps.stats(),
    )


@router.get("/strategies", response_model=list[StrategyInfo])
async def strategies(state: State) -> list[StrategyInfo]:
    """The next-pose strategies and which one requests get by default."""
    return [
        StrategyInfo(
            name=spec.name,
            description=spec.description,
            default=spec.name == state.context.default_strategy,
            needs_calibration=spec.needs_calibration,
        )
        for spec in STRATEGIES.values()
    ]


@router.post(
    "/next-pose",
    response_model=NextPoseResponse,
    responses=problem_responses(400, 404, 413, 422),
    openapi_extra={"requestBody": json_request_body(NextPoseRequest)},
)
async def plan(request: Request, state: State) -> Response:
    """One stateless search step: the next grid pose, whether the search is done, the current
    estimate of the target pose and why.

    Run on the event loop: a step is a few milliseconds of Python holding the GIL, so FastAPI's
    thread pool would add two thread hops per request and no parallelism. The body, which
    carries every view of the search so far, is validated by pydantic-core straight from its
    bytes (:func:`~services.optimizer.json_body.read_json`: half the cost of FastAPI's body
    parameter, same errors); the answer is serialised once by pydantic-core (returning the
    model would validate it again first).
    """
    body = await read_json(request, NextPoseRequest)
    answer = next_pose(body, state.context)
    return Response(answer.model_dump_json(), media_type="application/json")


@router.post("/map", response_model=MapResponse, responses=problem_responses(400, 413, 422))
def map_objects(body: MapRequest, state: State) -> MapResponse:
    """Ground positions of the detections of one view seen from a known pose (paper §3.2)."""
    return map_detections(body, state.context.calibrations)


@router.post(
    "/start-pose",
    response_model=StartPoseResponse,
    responses=problem_responses(400, 404, 413, 422),
    openapi_extra={"requestBody": json_request_body(StartPoseRequest)},
)
async def predict_start_pose(request: Request, state: State) -> Response:
    """The grid pose whose predicted view explains the target's detections best, before
    anything is rendered: where a hemisphere search without a given start takes its first view
    (``found``), or why not (``ambiguous``, ``failed``). Run on a worker thread: a scene's
    first request projects its objects into every grid pose (kept per scene), which takes
    seconds on a 1° grid, and a fine grid's scoring tens of milliseconds."""
    body = await read_json(request, StartPoseRequest)
    answer = await asyncio.to_thread(start_pose, body, state.context)
    return Response(answer.model_dump_json(), media_type="application/json")


@router.post(
    "/free-pose",
    response_model=FreePoseResponse,
    responses=problem_responses(400, 404, 413, 422),
)
def solve_free(body: FreePoseRequest, state: State) -> FreePoseResponse:
    """Any camera's pose (position, orientation, intrinsics) from the target's boxes alone:
    ``found``, ``ambiguous`` with the alternatives, or ``failed`` with why. Run on a worker
    thread: a solve is tens of milliseconds of numpy and scipy."""
    return free_pose(body, state.context.catalog, state.free_objects)


_BINARY = {"type": "string", "format": "binary"}


async def _form_parts(
    request: Request, path: str, names: tuple[str, ...], model: type[M]
) -> tuple[M, dict[str, bytes]]:
    """A form's parts (:mod:`services.common.contracts.refine`): the ``request`` part as
    ``model`` and the files ``names[1:]``, each refused with a problem naming it: not a form
    (415), a malformed form (400), a part missing or not valid (422)."""
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type != "multipart/form-data":
        raise UnsupportedMediaTypeError(
            f"POST {path} takes multipart/form-data with the parts "
            f"{', '.join(names)}; not {media_type or 'a body without a content type'}",
            field="content-type",
        )
    try:
        async with request.form(max_files=len(names) - 1, max_fields=1) as form:
            text = form.get("request")
            if isinstance(text, UploadFile):
                text = (await text.read()).decode("utf-8", errors="replace")
            files: dict[str, bytes] = {}
            for name in names[1:]:
                part = form.get(name)
                if not isinstance(part, UploadFile):
                    raise UnprocessableError(f"the form has no file '{name}'", field=name)
                files[name] = await part.read()
    except HTTPException as exc:  # how Starlette reports a malformed form inside an app
        raise BadRequestError(
            f"the multipart body is malformed: {exc.detail}", field="body"
        ) from exc
    if text is None:
        raise UnprocessableError("the form has no part 'request'", field="request")
    try:
        body = model.model_validate_json(text)
    except ValidationError as exc:
        error = exc.errors(include_url=False)[0]
        where = ".".join(str(part) for part in ("request", *error["loc"]))
        raise UnprocessableError(f"{where}: {error['msg']}", field=where) from exc
    return body, files


def _form_schema(
    names: tuple[str, ...], model: type[BaseModel], files: dict[str, str]
) -> dict[str, object]:
    """The OpenAPI request body of a form: the ``request`` part as ``model``'s JSON text and
    the binary ``files`` (by name, described)."""
    properties: dict[str, object] = {
        "request": {
            **model.model_json_schema(),
            "description": f"A {model.__name__} as JSON text.",
        },
        **{name: {**_BINARY, "description": files[name]} for name in names[1:]},
    }
    schema = {"type": "object", "required": list(names), "properties": properties}
    return {
        "requestBody": {"required": True, "content": {"multipart/form-data": {"schema": schema}}}
    }


@router.post(
    "/refine-pose",
    response_model=RefinePoseResponse,
    responses=problem_responses(400, 404, 413, 415, 422),
    openapi_extra=_form_schema(
        REFINE_PARTS,
        RefinePoseRequest,
        {
            "target": "The target: PNG, JPEG, PPM.",
            "render": "The render at the pose: the renderer's .npz (rgb, depth, objects).",
        },
    ),
)
async def refine(request: Request, state: State) -> Response:
    """A free pose refined densely against the target image by one render at it: the render's
    edges, back-projected through its depth, fitted onto the target's (and the focal length,
    when asked). Answers the refined pose and how the fit went (``fit.accepted``: use it). Run on
    a worker thread: a fit is a few hundred milliseconds of OpenCV and scipy."""
    body, files = await _form_parts(request, "/refine-pose", REFINE_PARTS, RefinePoseRequest)
    answer = await asyncio.to_thread(
        refine_pose,
        body,
        files["target"],
        files["render"],
        state.context.catalog,
        state.free_objects,
        state.image_limits,
        state.target_maps,
    )
    return Response(answer.model_dump_json(), media_type="application/json")


@router.post(
    "/refine-pose/target",
    response_model=TargetResponse,
    responses=problem_responses(400, 413, 415, 422),
    openapi_extra=_form_schema(
        TARGET_PARTS, TargetRequest, {"target": "The target: PNG, JPEG, PPM."}
    ),
)
async def prepare(request: Request, state: State) -> Response:
    """Make ready what a search's refinements will need of its target (its grey image on the
    renders' film, its distance maps) while its first render is made, so that the first
    ``/refine-pose`` finds them. Optional: a refinement makes them itself when they are not
    kept. Run on a worker thread: tens of milliseconds, a large photo's decoding included."""
    body, files = await _form_parts(request, "/refine-pose/target", TARGET_PARTS, TargetRequest)
    answer = await asyncio.to_thread(
        prepare_target, body, files["target"], state.image_limits, state.target_maps
    )
    return Response(answer.model_dump_json(), media_type="application/json")
