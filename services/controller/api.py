"""Controller routes: thin HTTP wrappers over search submission, the store, the runner, plots.

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
import contextlib
import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Annotated, Any, Final

from fastapi import APIRouter, Depends, Query, Request
from fastapi import Path as FastApiPath
from fastapi.responses import JSONResponse, Response, StreamingResponse
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.routing import BaseRoute, Match
from starlette.types import Scope

from services.common.auth import PROBE_PATHS
from services.common.contracts.base import MAX_SAFE_INTEGER
from services.common.contracts.optimize import UnsupportedGridError, searchable_grid
from services.common.contracts.render import SceneDetail, SceneSummary
from services.common.contracts.search import (
    MAX_ITERATIONS,
    TERMINAL_STATUSES,
    ControllerHealth,
    Search,
    SearchPage,
)
from services.common.errors import (
    ConflictError,
    NotFoundError,
    ServiceUnavailableError,
    UnauthorizedError,
    UnprocessableError,
)
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import GridIndex
from services.common.http import app_state, problem_responses
from services.common.stopping import STOPPING
from services.common.upload import read_upload
from services.controller.auth import authenticate, checked_key
from services.controller.broker import Broker, BrokerError
from services.controller.events import Notifier
from services.controller.form import OPENAPI, search_options
from services.controller.keys import ApiKey, KeyStore
from services.controller.page import (
    INDEX,
    SECURITY_HEADERS,
    Asset,
    PageAssets,
    accepts_gzip,
    not_modified,
)
from services.controller.plots import PlotCache, distance_png, trajectory_png
from services.controller.quotas import Quotas
from services.controller.runner import SearchRunner, StillStopping
from services.controller.settings import ControllerSettings
from services.controller.stages import StageError, Stages
from services.controller.store import SearchStore
from services.controller.submit import INLINE_WRITE_BYTES, create_search
from services.controller.transport import StageRequest
from services.controller.views import UnknownIteration, ViewStore, displayable, iteration_pose

__all__ = ["ControllerState", "needs_key", "router"]

router = APIRouter()
_log = logging.getLogger("cosmos.controller")

RETRY_AFTER_S = 5
"""``Retry-After`` of a 503 while a stage is unavailable (the broker probes it more often)."""


@dataclass(frozen=True)
class ControllerState:
    settings: ControllerSettings
    store: SearchStore
    broker: Broker
    stages: Stages
    runner: SearchRunner
    notifier: Notifier
    keys: KeyStore
    quotas: Quotas
    views: ViewStore
    plots: PlotCache = field(default_factory=PlotCache)
    page: PageAssets = field(default_factory=PageAssets)


State = Annotated[ControllerState, Depends(app_state("controller"))]

_bearer = HTTPBearer(
    scheme_name="ApiKey",
    bearerFormat="cosmos_<43 characters>",
    description="An API key: `cosmos keys create` makes one (`cosmos up` prints a local one).",
    auto_error=False,
)


async def _caller(
    request: Request,
    state: State,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> ApiKey | None:
    """The key a request acts for; None when auth is off (everyone's searches, no quotas).
    ``credentials`` only declares the scheme in the OpenAPI schema: the check is
    :func:`~services.controller.auth.authenticate`'s, done already for a request with a body."""
    if not state.settings.controller_auth:
        return None
    return checked_key(request.scope) or authenticate(
        state.keys, request.headers.get("authorization")
    )


Caller = Annotated[ApiKey | None, Depends(_caller)]


def _wants_key(route: BaseRoute) -> bool:
    """Whether ``route`` checks an API key (depends on :func:`_caller`, directly or not)."""
    if not isinstance(route, APIRoute):
        return False  # not a FastAPI route: no dependencies, no key
    pending = [route.dependant]
    while pending:
        dependant = pending.pop()
        if dependant.call is _caller:
            return True
        pending.extend(dependant.dependencies)
    return False


def needs_key(scope: Scope) -> bool:
    """Whether a request to ``scope``'s path wants an API key before its body is read: the
    route of this module that takes it checks one (its method aside, so a wrong method gets
    its 405 where the path is open), or no route takes the path at all (the probes and the
    OpenAPI documents are open)."""
    partial: BaseRoute | None = None
    for route in router.routes:  # in order, as the app dispatches
        match, _ = route.matches(scope)
        if match is Match.FULL:
            return _wants_key(route)
        if match is Match.PARTIAL and partial is None:
            partial = route
    if partial is not None:
        return _wants_key(partial)
    app = scope["app"]
    documents = {app.openapi_url, app.docs_url, app.redoc_url, app.swagger_ui_oauth2_redirect_url}
    return scope["path"] not in PROBE_PATHS | documents


def _visible_to(key: ApiKey | None) -> str | None:
    """The owner whose searches ``key`` sees (None: everyone's, for admin keys or no auth)."""
    return None if key is None or key.admin else key.id


def _unknown_search(search_id: str) -> NotFoundError:
    return NotFoundError(
        f"no search {search_id!r}", field="id", slug="unknown-search", title="Unknown search"
    )


def _search_or_404(state: ControllerState, key: ApiKey | None, search_id: str) -> Search:
    search = state.store.get(search_id, visible_to=_visible_to(key))
    if search is None:
        raise _unknown_search(search_id)
    return search


def _sees_store(state: ControllerState, request: Request) -> bool:
    """Whether ``request`` may see the store's figures: it carries an admin key (or keys are
    off). Any other key, a wrong one or none gets the open health: a health check is never
    refused."""
    if not state.settings.controller_auth:
        return True
    authorization = request.headers.get("authorization")
    if authorization is None:
        return False
    try:
        return authenticate(state.keys, authorization).admin
    except UnauthorizedError:
        return False


@router.get("/health", response_model=ControllerHealth)
async def health(request: Request, state: State) -> ControllerHealth:
    """Liveness, the queue, what the broker knows of every replica by name (state, tasks in
    flight, moving-average task times; ``degraded``, naming the stages, while a stage has no
    replica available). Open to anyone (no key): health checks have none, and no search or
    internal address is shown. The store's size (``store_searches``, ``store_image_bytes``,
    ``store_bytes``: every tenant's) only with an admin key (``Authorization: Bearer <key>``);
    null for any other key or none."""
    return _health_of(state, with_store=_sees_store(state, request))


HEALTH_EVENTS_EVERY_S: Final = 1.0
"""How often ``GET /health/events`` looks whether the health changed."""
_KEEP_ALIVE_S: Final = 15.0
"""A comment sent on an event stream after this long without an event."""
_STOP_CHECK_S: Final = 1.0
"""How often a waiting event stream looks whether the server is stopping (:data:`STOPPING`)."""


async def _set_within(event: asyncio.Event, timeout_s: float) -> bool:
    """Whether ``event`` is set within ``timeout_s``."""
    try:
        await asyncio.wait_for(event.wait(), timeout=timeout_s)
    except TimeoutError:
        return False
    return True


@router.get(
    "/health/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def health_events(request: Request, state: State) -> StreamingResponse:
    """Server-sent events: ``health``, the body ``GET /health`` answers, at once and then
    whenever it changed (looked at every second), until the client leaves or the server stops;
    a comment every 15 s while nothing changed keeps proxies from closing the stream. The web
    page's broker panel follows it. Open to anyone, as ``/health`` is, and with the store's
    figures for an admin key only, as there."""
    with_store = _sees_store(state, request)

    async def stream() -> AsyncIterator[bytes]:
        last = ""
        quiet_s = 0.0
        while not STOPPING.is_set():
            doc = _health_of(state, with_store=with_store).model_dump_json()
            if doc != last:
                last = doc
                quiet_s = 0.0
                yield _sse("health", doc)
            elif quiet_s >= _KEEP_ALIVE_S:
                quiet_s = 0.0
                yield b": keep-alive\n\n"
            await asyncio.sleep(HEALTH_EVENTS_EVERY_S)
            quiet_s += HEALTH_EVENTS_EVERY_S

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )


def _health_of(state: ControllerState, *, with_store: bool) -> ControllerHealth:
    size = state.store.size() if with_store else None
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
    dependencies=[Depends(_caller)],
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


def _refuse_while_unavailable(state: ControllerState) -> None:
    """503 with ``Retry-After`` while a stage no replica serves: a search taken now would only
    wait for it (and fail after the outage budget), so it is not taken."""
    down = state.broker.unavailable()
    if down:
        raise ServiceUnavailableError(
            f"the {' and the '.join(down)} {'is' if len(down) == 1 else 'are'} unavailable (no "
            "replica answers); try again once GET /health no longer lists "
            f"{'it' if len(down) == 1 else 'them'}",
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
    _refuse_while_unavailable(state)
    upload = await read_upload(request)
    options = search_options(upload.fields, request.query_params.multi_items())
    admitted: contextlib.AbstractContextManager[None] = (
        state.quotas.admit(key.id, len(upload.image))
        if key is not None and not key.admin
        else contextlib.nullcontext()
    )
    idle = state.runner.idle
    try:
        with admitted:
            search = await create_search(
                state.store,
                state.stages,
                image=upload.image,
                scene_id=options.scene,
                strategy=options.strategy,
                start_theta_deg=options.start_theta_deg,
                start_phi_deg=options.start_phi_deg,
                seed=options.seed,
                max_iterations=options.max_iterations
                or state.settings.controller_default_max_iterations,
                max_image_pixels=state.settings.controller_max_image_pixels,
                max_image_side=state.settings.controller_max_image_side,
                start_early=idle,
                owner=None if key is None else key.id,
            )
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:
        raise UnprocessableError(str(exc), field="scene") from exc
    # The runner keeps the image of a search that starts now, or a small one; a large image of
    # a queued search is read back when it starts (50 maximal uploads queued would hold 1 GB).
    keep = idle or len(upload.image) <= INLINE_WRITE_BYTES
    state.runner.submit(search.id, recorded=(search, upload.image) if keep else None)
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
    items, total = state.store.page(limit, offset, visible_to=_visible_to(key))
    return SearchPage(items=tuple(items), total=total, limit=limit, offset=offset)


@router.get("/searches/{search_id}", response_model=Search, responses=problem_responses(401, 404))
async def get_search(search_id: str, state: State, key: Caller) -> Search:
    """A search: status, iterations so far, result or error."""
    return _search_or_404(state, key, search_id)


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
    search = _search_or_404(state, key, search_id)
    if search.status not in TERMINAL_STATUSES:
        cancelled = state.runner.cancel(search_id)
        return JSONResponse(cancelled.model_dump(mode="json"))
    try:
        deleted = state.runner.delete(search_id)
    except StillStopping:
        raise ConflictError(
            f"search {search_id} was cancelled and is still stopping; delete it again in a moment",
            slug="search-stopping",
            title="Search still stopping",
            headers={"Retry-After": "1"},
        ) from None
    if deleted is None:  # expired meanwhile
        raise _unknown_search(search_id)
    owner, created_at = deleted
    if owner is not None:
        state.quotas.deleted(owner, created_at)
    return Response(status_code=204)


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
    why = state.runner.why_not_retryable(_search_or_404(state, key, search_id))
    if why is not None:
        raise ConflictError(why, slug="not-retryable", title="Not retryable")
    _refuse_while_unavailable(state)
    if key is not None and not key.admin:
        state.quotas.check(key.id, 0)  # its image is stored already
    search = state.runner.retry(search_id)  # nothing ran since the check: it takes the search
    return JSONResponse(
        search.model_dump(mode="json"),
        status_code=202,
        headers={"Location": f"/searches/{search.id}"},
    )


def _sse(event: str, data: str) -> bytes:
    return f"event: {event}\ndata: {data}\n\n".encode()


@router.get(
    "/searches/{search_id}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}, **problem_responses(401, 404)},
)
async def search_events(search_id: str, state: State, key: Caller) -> StreamingResponse:
    """Server-sent events (:data:`~services.common.contracts.search.SEARCH_EVENTS`): while the
    search is queued or running, ``search`` with the search without its iterations whenever it
    changed (its status, its target's detections); ``iteration`` for each recorded iteration;
    then one ``end`` with the search without its iterations. The stored JSON documents are sent
    as they are. A server that stops ends the stream (the client follows again, elsewhere)."""
    if state.store.status_doc(search_id, visible_to=_visible_to(key)) is None:
        raise _unknown_search(search_id)

    async def stream() -> AsyncIterator[bytes]:
        sent = 0
        last_doc = ""
        with state.notifier.following(search_id):  # a client that goes away stops following
            while True:
                changed = state.notifier.current(search_id)
                # The status before the iterations: a search ends after its last one.
                status_doc = state.store.status_doc(search_id)
                if status_doc is not None and status_doc[0] not in TERMINAL_STATUSES:
                    if status_doc[1] != last_doc:
                        last_doc = status_doc[1]
                        yield _sse("search", last_doc)
                docs = state.store.iteration_docs(search_id, start=sent)
                for doc in docs:
                    yield _sse("iteration", doc)
                sent += len(docs)
                if status_doc is None:  # expired meanwhile: stop rather than spin
                    return
                if status_doc[0] in TERMINAL_STATUSES:
                    yield _sse("end", status_doc[1])
                    return
                quiet_s = 0.0
                while not await _set_within(changed, _STOP_CHECK_S):
                    if STOPPING.is_set():
                        return  # the server is stopping: the client follows again elsewhere
                    quiet_s += _STOP_CHECK_S
                    if quiet_s >= _KEEP_ALIVE_S:
                        quiet_s = 0.0
                        yield b": keep-alive\n\n"

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )


async def _grid_of(state: ControllerState, search: Search) -> GridSpec:
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
    search = _search_or_404(state, key, search_id)

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
    search = _search_or_404(state, key, search_id)

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
    dependencies=[Depends(_caller)],
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
    dependencies=[Depends(_caller)],
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
    _search_or_404(state, key, search_id)
    try:
        image = state.store.image(search_id)
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
    seed). 404 for an iteration not recorded (yet)."""
    search = _search_or_404(state, key, search_id)
    try:
        pose = iteration_pose(search, index)
        settings = state.stages.settings_for(search.view_settings)
        png = await state.views.png(search.scene, pose, settings)
    except UnknownIteration as exc:
        raise NotFoundError(
            str(exc), field="index", slug="unknown-iteration", title="Unknown iteration"
        ) from exc
    except BrokerError as exc:
        raise _unavailable(exc.stage, exc) from exc
    except StageError as exc:  # the scene file changed or went away since the search
        raise _stage_refusal(exc, "scene") from exc
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


def _file(request: Request, asset: Asset) -> Response:
    """``asset`` for ``request``: 304 when the client holds it, gzipped when it accepts that."""
    gzip_ok = accepts_gzip(request.headers.get("accept-encoding", ""))
    headers = {**asset.headers(gzip_ok=gzip_ok), **SECURITY_HEADERS}
    if not_modified(asset, request.headers.get("if-none-match", "")):
        headers.pop("Content-Encoding", None)
        return Response(status_code=304, headers=headers)
    body = asset.gzipped if gzip_ok and asset.gzipped is not None else asset.body
    return Response(body, media_type=asset.media_type, headers=headers)


def _page_missing(what: str) -> NotFoundError:
    return NotFoundError(
        f"{what} is not built: run `npm ci && npm run build` in web/",
        slug="page-not-built",
        title="Page not built",
    )


@router.get("/", response_class=Response, include_in_schema=False)
async def page(request: Request, state: State) -> Response:
    """The web page (no key needed to load it: it asks for one and sends it with its calls)."""
    if state.page.index is None:
        raise _page_missing(INDEX)
    return _file(request, state.page.index)


@router.get("/assets/{name}", response_class=Response, include_in_schema=False)
async def page_asset(name: str, request: Request, state: State) -> Response:
    """A file of the web page (its name carries a hash of its content: cached for good)."""
    asset = state.page.asset(name)
    if asset is None:
        raise NotFoundError(f"no page asset {name!r}", field="name", slug="unknown-asset")
    return _file(request, asset)
