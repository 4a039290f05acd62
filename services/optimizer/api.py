"""Optimizer routes: thin HTTP wrappers over planning (:mod:`services.optimizer.planning`) and the
free pose (:mod:`services.optimizer.free_pose`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, get_args

from fastapi import APIRouter, Depends, Request, Response

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
from services.common.http import app_state, problem_responses
from services.optimizer.free_pose import SceneObjectCache, free_pose
from services.optimizer.json_body import json_request_body, read_json
from services.optimizer.planning import OptimizerContext, map_detections, next_pose
from services.optimizer.strategies import STRATEGIES

__all__ = ["OptimizerState", "router"]

router = APIRouter()


@dataclass(frozen=True)
class OptimizerState:
    """What the routes need, built in the app's lifespan."""

    context: OptimizerContext
    free_objects: SceneObjectCache = field(default_factory=SceneObjectCache)


State = Annotated[OptimizerState, Depends(app_state("optimizer"))]


@router.get("/health", response_model=OptimizerHealth)
async def health(state: State) -> OptimizerHealth:
    """Liveness, the strategies on offer and the stored paper calibrations."""
    return OptimizerHealth(
        status="ok",
        service="optimizer",
        strategies=get_args(StrategyName),
        default_strategy=state.context.default_strategy,
        paper_calibrations=len(state.context.calibrations),
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
    "/free-pose",
    response_model=FreePoseResponse,
    responses=problem_responses(400, 404, 413, 422),
)
def solve_free(body: FreePoseRequest, state: State) -> FreePoseResponse:
    """Any camera's pose (position, orientation, intrinsics) from the target's boxes alone:
    ``found``, ``ambiguous`` with the alternatives, or ``failed`` with why. Run on a worker
    thread: a solve is tens of milliseconds of numpy and scipy."""
    return free_pose(body, state.context.catalog, state.free_objects)
