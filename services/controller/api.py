"""Controller routes: each validates its request, calls one function (admission, the store, the
runner, the event streams, plots, views) and maps its errors to problem details.

Every route but ``/health`` and ``/health/events`` (and the OpenAPI documents, and the web
page's files, which hold no data) wants an API key (``Authorization: Bearer <key>``,
:mod:`services.controller.keys`) unless ``COSMOS_CONTROLLER_AUTH`` is off. ``/health`` stays
open for load balancers and container health checks; it tells whether the service is up, its
queue and replicas by name (``renderer-1``), no search and no address (those are in the
controller's log, for every key alike); the store's figures, every tenant's, only with an admin
key. A key sees, cancels and deletes its own searches only (another tenant's is a 404, as an
unknown one, so ids do not leak); an admin key sees them all.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi import Path as FastApiPath
from fastapi.responses import JSONResponse, Response
from sse_starlette import EventSourceResponse

from services.common.base import MAX_SAFE_INTEGER
from services.common.contracts.optimize import UnsupportedGridError, searchable_grid
from services.common.contracts.render import SceneDetail, SceneSummary
from services.common.contracts.search import (
    MAX_ITERATIONS,
    ControllerHealth,
    Search,
    SearchPage,
)
from services.common.errors import (
    ConflictError,
    NotFoundError,
    ServiceUnavailableError,
    UnprocessableError,
)
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import GridIndex
from services.common.http import app_state, problem_responses
from services.common.upload import read_upload
from services.controller import events
from services.controller.auth import Caller, caller, is_admin
from services.controller.broker import BrokerError
from services.controller.events import event_stream
from services.controller.form import OPENAPI, search_options
from services.controller.keys import ApiKey
from services.controller.page import page_routes
from services.controller.plots import distance_png, trajectory_png
from services.controller.runner import NotRetryable, StillStopping
from services.controller.stages import StageError
from services.controller.submit import RETRY_AFTER_S
from services.controller.transport import StageRequest
from services.controller.views import UnknownIteration, displayable, iteration_pose, to_png
from services.controller.wiring import Controller

__all__ = ["router"]

router = APIRouter()
_log = logging.getLogger("cosmos.controller")

State = Annotated[Controller, Depends(app_state("controller"))]


def _visible_to(key: ApiKey | None) -> str | None:
    """The owner whose searches ``key`` sees (None: everyone's, for admin keys or no auth)."""
    return None if key is None or key.admin else key.id


def _unknown_search(search_id: str) -> NotFoundError:
    return NotFoundError(
        f"no search {search_id!r}", field="id", slug="unknown-search", title="Unknown search"
    )


async def _search_or_404(state: Controller, key: ApiKey | None, search_id: str) -> Search:
    # The store is read on threads here: a database that hangs holds this request only, never
    # the event loop (and with it every request and search of the controller).
    search = await asyncio.to_thread(state.store.get, search_id, visible_to=_visible_to(key))
    if search is None:
        raise _unknown_search(search_id)
    return search


async def _sees_store(state: Controller, request: Request) -> bool:
    """Whether ``request`` may see the store's figures (every tenant's): with an admin key, or
    when keys are off."""
    if not state.settings.controller_auth:
        return True
    return await asyncio.to_thread(is_admin, state.keys, request.headers.get("authorization"))


@router.get("/health", response_model=ControllerHealth)
async def health(request: Request, state: State) -> ControllerHealth:
    """Liveness, the queue, what the broker knows of every replica by name (state, tasks in
    flight, moving-average task times; ``degraded``, naming the stages, while a stage has no
    replica available). Open to anyone (no key): health checks have none, and no search or
    internal address is shown. The store's size (``store_searches``, ``store_image_bytes``,
    ``store_bytes``: every tenant's) only with an admin key (``Authorization: Bearer <key>``);
    null for any other key or none."""
    return await _health_of(state, with_store=await _sees_store(state, request))


@router.get(
    "/health/events",
    response_class=EventSourceResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def health_events(request: Request, state: State) -> EventSourceResponse:
    """Server-sent events: ``health``, the body ``GET /health`` answers, at once and then
    whenever it changed (looked at every second), until the client leaves or the server stops;
    a comment every 15 s keeps proxies from closing the stream. The web page's broker panel
    follows it. Open to anyone, as ``/health`` is, and with the store's figures for an admin
    key only, as there."""
    with_store = await _sees_store(state, request)

    async def health() -> str:
        return (await _health_of(state, with_store=with_store)).model_dump_json()

    return event_stream(events.health_events(health))


async def _health_of(state: Controller, *, with_store: bool) -> ControllerHealth:
    size = await asyncio.to_thread(state.store.size) if with_store else None
    unavailable = tuple(state.broker.unavailable())
    return ControllerHealth(
        status="degraded" if unavailable else "ok",
        service="controller",
        searches_queued=state.runner.queued,
        searches_running=state.runner.running,
        broker_heuristic=state.broker.heuristic.value,
        replicas=tuple(state.broker.stats()),
        store_searches=None if size is None else size.searches,
        store_image_bytes=None if size is None else size.image_bytes,
        store_bytes=None if size is None else size.database_bytes,
        unavailable_stages=unavailable,
    )


@router.get(
    "/scenes",
    response_model=list[SceneSummary],
    responses=problem_responses(401, 503),
    dependencies=[Depends(caller)],
)
async def scenes(state: State) -> Any:
    """The scenes the renderers know (proxied)."""
    try:
        response = await state.broker.call("renderer", "scene", StageRequest("GET", "/scenes"))
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    return JSONResponse(response.json(), status_code=response.status_code)


def _unavailable(stage: str, why: Exception) -> ServiceUnavailableError:
    """A 503 for a request that ``stage`` could not serve. ``why`` names replica addresses: it
    goes to the log only."""
    _log.warning("the %s could not serve a request: %s", stage, why)
    return ServiceUnavailableError(
        f"the {stage} is unavailable: no replica could serve the request; try again later "
        "(GET /health lists the stages no replica serves)",
        slug="stage-unavailable",
        title="Stage unavailable",
        headers={"Retry-After": str(RETRY_AFTER_S)},
    )


@router.post(
    "/searches",
    status_code=202,
    response_model=Search,
    responses=problem_responses(400, 401, 404, 413, 415, 422, 429, 503),
    openapi_extra=OPENAPI,
)
async def submit(request: Request, state: State, key: Caller) -> JSONResponse:
    """Start a search for where ``image`` was taken in ``scene``; answers 202 and a Location.

    The image is a form's file field ``image`` with the options as text fields, or the raw PNG,
    JPEG or binary PPM body with the options in the query. A key over one of its quotas gets
    429 with ``Retry-After``; while a stage has no replica available (``GET /health`` says
    ``degraded``), 503 with ``Retry-After``."""
    state.admission.refuse_while_unavailable()  # before the body is read
    upload = await read_upload(request)
    options = search_options(upload.fields, request.query_params.multi_items())
    try:
        search = await state.admission.submit(upload.image, options, key)
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:
        raise UnprocessableError(str(exc), field="scene") from exc
    return JSONResponse(
        search.model_dump(mode="json"),
        status_code=202,
        headers={"Location": f"/searches/{search.id}"},
    )


@router.get("/searches", response_model=SearchPage, responses=problem_responses(401))
async def list_searches(
    state: State,
    key: Caller,
    limit: Annotated[int, Query(ge=1, le=200)] = 20,
    offset: Annotated[int, Query(ge=0, le=MAX_SAFE_INTEGER)] = 0,
) -> SearchPage:
    """The key's searches (an admin key's: everyone's), newest first, without iterations."""
    items, total = await asyncio.to_thread(
        state.store.page, limit, offset, visible_to=_visible_to(key)
    )
    return SearchPage(items=tuple(items), total=total, limit=limit, offset=offset)


@router.get("/searches/{search_id}", response_model=Search, responses=problem_responses(401, 404))
async def get_search(search_id: str, state: State, key: Caller) -> Search:
    """A search: status, iterations so far, result or error."""
    return await _search_or_404(state, key, search_id)


@router.delete(
    "/searches/{search_id}",
    response_model=Search,
    responses={
        200: {"description": "The queued or running search, now cancelled (it is kept)."},
        204: {"description": "The finished, failed or cancelled search was deleted."},
        **problem_responses(401, 404, 409),
    },
)
async def cancel_search(search_id: str, state: State, key: Caller) -> Response:
    """Cancel a queued or running search: 200, the search cancelled (its iterations so far are
    kept, and its image counts towards the key's stored bytes until it is deleted). Delete a
    finished, failed or cancelled search with its target image and iterations: 204, and its
    bytes no longer count. So a first DELETE cancels a running search and a second one deletes
    it; a DELETE that arrives just after the search ended deletes it. 409 with ``Retry-After``
    while a search cancelled a moment ago is still stopping."""
    search = await _search_or_404(state, key, search_id)
    try:
        cancelled = state.admission.dismiss(search)
    except StillStopping:
        raise ConflictError(
            f"search {search_id} was cancelled and is still stopping; delete it again in a moment",
            slug="search-stopping",
            title="Search still stopping",
            headers={"Retry-After": "1"},
        ) from None
    except KeyError:  # expired meanwhile
        raise _unknown_search(search_id) from None
    if cancelled is None:
        return Response(status_code=204)
    return JSONResponse(cancelled.model_dump(mode="json"))


@router.post(
    "/searches/{search_id}/retry",
    status_code=202,
    response_model=Search,
    responses=problem_responses(401, 404, 409, 429, 503),
)
async def retry_search(search_id: str, state: State, key: Caller) -> JSONResponse:
    """Resume a search that failed because a stage was unavailable (its error's ``type`` is
    ``urn:cosmos:problem:stage-unavailable``) from its recorded iterations: 202, the search
    queued again. 409 for any other search; 503 with ``Retry-After`` while a stage is still
    unavailable; 429 for a key at its quota of searches queued or running."""
    try:
        search = state.admission.retry(await _search_or_404(state, key, search_id), key)
    except NotRetryable as exc:
        raise ConflictError(str(exc), slug="not-retryable", title="Not retryable") from exc
    return JSONResponse(
        search.model_dump(mode="json"),
        status_code=202,
        headers={"Location": f"/searches/{search.id}"},
    )


@router.get(
    "/searches/{search_id}/events",
    response_class=EventSourceResponse,
    responses={200: {"content": {"text/event-stream": {}}}, **problem_responses(401, 404)},
)
async def search_events(search_id: str, state: State, key: Caller) -> EventSourceResponse:
    """Server-sent events (:data:`~services.common.contracts.search.SEARCH_EVENTS`): while the
    search is queued or running, ``search`` with the search without its iterations whenever it
    changed (its status, its target's detections); ``iteration`` for each recorded iteration;
    then one ``end`` with the search without its iterations. The stored JSON documents are sent
    as they are. A server that stops ends the stream (the client follows again, elsewhere)."""
    found = await asyncio.to_thread(state.store.status_doc, search_id, visible_to=_visible_to(key))
    if found is None:
        raise _unknown_search(search_id)
    return event_stream(events.search_events(state.store, state.notifier, search_id))


async def _grid_of(state: Controller, search: Search) -> GridSpec:
    try:
        scene = await state.stages.scene(search.scene)
    except (StageError, BrokerError) as exc:
        raise _unavailable("renderer", exc) from exc
    try:
        return searchable_grid(scene.spec.search)
    except UnsupportedGridError as exc:  # the scene file changed since the search was taken
        raise UnprocessableError(
            f"scene {search.scene!r}'s grid cannot be drawn: {exc}",
            field=exc.field,
            slug="unsupported-grid",
            title="Grid not supported",
        ) from exc


@router.get(
    "/searches/{search_id}/trajectory.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, **problem_responses(401, 404, 422, 503)},
)
async def trajectory(search_id: str, state: State, key: Caller) -> Response:
    """The camera's path on the hemisphere (like the paper's Fig. 6)."""
    search = await _search_or_404(state, key, search_id)

    async def draw() -> bytes:
        grid = (await _grid_of(state, search)).grid()
        return await asyncio.to_thread(trajectory_png, search, grid)

    return Response(await state.plots.png(search, "trajectory", draw), media_type="image/png")


@router.get(
    "/searches/{search_id}/distance.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, **problem_responses(401, 404)},
)
async def distance(search_id: str, state: State, key: Caller) -> Response:
    """Angle to the estimate per iteration (like the paper's Fig. 8)."""
    search = await _search_or_404(state, key, search_id)

    async def draw() -> bytes:
        return await asyncio.to_thread(distance_png, search)

    return Response(await state.plots.png(search, "distance", draw), media_type="image/png")


def _stage_refusal(exc: StageError, field: str) -> NotFoundError | UnprocessableError:
    """A renderer's refusal as the page's problem: an unknown scene is a 404, anything else
    (a grid pose off the grid) a 422 naming the renderer's field."""
    detail = exc.problem.detail or exc.problem.title
    if exc.problem.status == 404:
        return NotFoundError(detail, field=field, slug="unknown-scene", title="Unknown scene")
    return UnprocessableError(detail, field=exc.problem.field or field)


_PNG_ANSWER: dict[int | str, dict[str, Any]] = {200: {"content": {"image/png": {}}}}


@router.get(
    "/scenes/{scene_id}",
    response_model=SceneDetail,
    responses=problem_responses(401, 404, 503),
    dependencies=[Depends(caller)],
)
async def scene(scene_id: str, state: State) -> SceneDetail:
    """A scene's spec and its hemisphere grid with its rings (the page draws them)."""
    try:
        return await state.stages.scene(scene_id)
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:
        raise _stage_refusal(exc, "scene_id") from exc


@router.get(
    "/scenes/{scene_id}/view.png",
    response_class=Response,
    responses={**_PNG_ANSWER, **problem_responses(401, 404, 422, 503)},
    dependencies=[Depends(caller)],
)
async def scene_view(
    scene_id: str,
    state: State,
    lat: Annotated[int, Query(ge=0, le=MAX_SAFE_INTEGER, description="Ring of the grid pose.")],
    lon: Annotated[int, Query(ge=0, le=MAX_SAFE_INTEGER, description="Pose on the ring.")],
) -> Response:
    """The scene seen from grid pose (``lat``, ``lon``), rendered as a search's views are (the
    page's scene preview, and a target made by picking a pose)."""
    try:
        index = GridIndex(lat=lat, lon=lon)
        png = await state.views.png(scene_id, index, state.stages.view_settings)
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:
        raise _stage_refusal(exc, "scene_id") from exc
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


@router.get(
    "/searches/{search_id}/target",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}, "image/jpeg": {}}},
        **problem_responses(401, 404),
    },
)
async def search_target(search_id: str, state: State, key: Caller) -> Response:
    """The search's target image as uploaded (a PPM as PNG); 404 once it is no longer held
    (a failed search's is deleted when it fails)."""
    await _search_or_404(state, key, search_id)
    try:
        image = await asyncio.to_thread(state.store.image, search_id)
    except KeyError:
        raise NotFoundError(
            f"search {search_id} no longer holds its target image (a failed search's is deleted)",
            field="id",
            slug="target-gone",
            title="Target image gone",
        ) from None
    body, media_type = await asyncio.to_thread(displayable, image)
    return Response(body, media_type=media_type, headers={"Cache-Control": "private, max-age=3600"})


@router.get(
    "/searches/{search_id}/iterations/{index}/view.png",
    response_class=Response,
    responses={**_PNG_ANSWER, **problem_responses(401, 404, 422, 503)},
)
async def iteration_view(
    search_id: str,
    index: Annotated[int, FastApiPath(ge=0, le=MAX_ITERATIONS, description="Iteration index.")],
    state: State,
    key: Caller,
) -> Response:
    """The view the search rendered at iteration ``index``: kept from the search, or rendered
    again, identically (the same scene, grid pose, and the film and samples the search recorded
    when it was submitted, whatever the controller's settings now; and the renderer's fixed
    seed; a free search's camera on the film it was rendered on). 404 for an iteration not
    recorded (yet)."""
    search = await _search_or_404(state, key, search_id)
    try:
        pose = iteration_pose(search, index)
        settings = state.stages.settings_for(search.view_settings)
        camera = search.iterations[index].camera
        if camera is None:
            png = await state.views.png(search.scene, pose, settings)
        else:  # a free search's view: its camera on its film, rendered again (not kept)
            size = search.iterations[index].image_size
            image = await state.stages.render_camera(search.scene, camera, size, "", settings)
            png = await asyncio.to_thread(to_png, image)
    except UnknownIteration as exc:
        raise NotFoundError(
            str(exc), field="index", slug="unknown-iteration", title="Unknown iteration"
        ) from exc
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:  # the scene file changed or went away since the search
        raise _stage_refusal(exc, "scene") from exc
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


router.routes.extend(page_routes())  # the page: no key needed to load it (page.py)
