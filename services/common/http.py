"""HTTP plumbing shared by the services: problem+json handlers, a request body size limit, the
service token (:mod:`services.common.auth`) and the liveness and readiness probes.

Every error leaves a service as ``application/problem+json`` (RFC 9457): domain errors
(:class:`~services.common.errors.ServiceError`), request validation errors, Starlette's own HTTP
errors, and, as a last resort, unexpected exceptions (500, without internals).

Every service answers ``GET /livez`` (the process answers: restart it if not) and
``GET /readyz`` (it can serve now: send it work if so; 503 with the reasons if not), the way
Kubernetes' probes and ``docker compose`` health checks ask. ``GET /health`` says more, for people
and the controller's broker.
"""

from __future__ import annotations

import gc
import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.common.auth import (
    MissingServiceTokenError,
    ServiceTokenMiddleware,
    ServiceTokenSettings,
    declare_service_token,
)
from services.common.contracts.base import FrozenModel
from services.common.errors import (
    PayloadTooLargeError,
    ProblemDetails,
    ServiceError,
    ServiceUnavailableError,
    problem_type,
)
from services.common.openapi import publish_plain_schema

__all__ = [
    "PROBLEM_JSON",
    "allowed_methods",
    "app_state",
    "freeze_heap",
    "service_app",
    "single_query_values",
    "BodySizeLimitMiddleware",
    "Probe",
    "ProblemResponse",
    "Readiness",
    "install_problem_handlers",
    "problem_responses",
]

PROBLEM_JSON = "application/problem+json"
_log = logging.getLogger("cosmos.http")


class ProblemResponse(JSONResponse):
    media_type = PROBLEM_JSON


def _respond(problem: ProblemDetails, headers: dict[str, str] | None = None) -> ProblemResponse:
    return ProblemResponse(
        problem.model_dump(mode="json", exclude_none=True),
        status_code=problem.status,
        headers=headers,
    )


def _field_of(loc: tuple[int | str, ...]) -> str:
    """``("body", "pose", "theta_deg")`` -> ``pose.theta_deg``; list indices as ``[i]``."""
    parts = list(loc[1:] if loc and loc[0] in {"body", "query", "path", "header"} else loc)
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else ("." if out else "") + str(part)
    return out or str(loc[0] if loc else "body")


async def _service_error(request: Request, exc: Exception) -> ProblemResponse:
    if not isinstance(exc, ServiceError):  # registered for this type only
        raise exc
    headers = exc.headers or ({"Retry-After": "1"} if exc.status == 503 else None)
    return _respond(exc.problem(instance=request.url.path), headers)


async def _validation_error(request: Request, exc: Exception) -> ProblemResponse:
    if not isinstance(exc, RequestValidationError):  # registered for this type only
        raise exc
    errors = [
        {"field": _field_of(tuple(err.get("loc", ()))), "message": err.get("msg", "invalid")}
        for err in exc.errors()
    ]
    first = errors[0] if errors else {"field": "body", "message": "invalid request"}
    detail = f"{first['field']}: {first['message']}"
    if len(errors) > 1:
        detail += f" (and {len(errors) - 1} more)"
    return _respond(
        ProblemDetails(
            type=problem_type("invalid-request"),
            title="Invalid request",
            status=422,
            detail=detail,
            instance=request.url.path,
            field=first["field"],
            errors=errors,
        )
    )


_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def allowed_methods(request: Request) -> list[str]:
    """Every method a route of the app answers at the request's path. Starlette's 405 names
    only the methods of the first route whose path matched (``GET`` for a path that also takes
    ``DELETE``), so each method is matched against every route."""
    allowed = []
    for method in _METHODS:
        scope = {
            "type": "http",
            "path": request.scope["path"],
            "root_path": request.scope.get("root_path", ""),
            "method": method,
            "headers": [],
            "query_string": b"",
        }
        if any(route.matches(scope)[0] is Match.FULL for route in request.app.router.routes):
            allowed.append(method)
    return allowed


async def _http_error(request: Request, exc: Exception) -> ProblemResponse:
    if not isinstance(exc, StarletteHTTPException):  # registered for this type only
        raise exc
    title = {404: "Not found", 405: "Method not allowed"}.get(exc.status_code, "HTTP error")
    headers = dict(exc.headers) if exc.headers else {}
    detail = str(exc.detail)
    if exc.status_code == 405:
        allowed = ", ".join(allowed_methods(request))
        headers["Allow"] = allowed
        detail = f"{request.method} is not allowed here; allowed: {allowed}"
    return _respond(
        ProblemDetails(
            type="about:blank",
            title=title,
            status=exc.status_code,
            detail=detail,
            instance=request.url.path,
        ),
        headers or None,
    )


async def _unexpected_error(request: Request, exc: Exception) -> ProblemResponse:
    _log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return _respond(
        ProblemDetails(
            type=problem_type("internal-error"),
            title="Internal error",
            status=500,
            detail="The service failed unexpectedly; the error was logged.",
            instance=request.url.path,
        )
    )


def install_problem_handlers(app: FastAPI) -> None:
    """Make every error ``app`` raises answer with problem+json."""
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries declaring problem+json bodies for ``statuses``."""
    schema = ProblemDetails.model_json_schema()
    return {
        status: {
            "description": "Problem details (RFC 9457)",
            "content": {PROBLEM_JSON: {"schema": schema}},
        }
        for status in statuses
    }


class BodySizeLimitMiddleware:
    """Reject request bodies over ``max_bytes`` with 413, by Content-Length or by counting.

    A declared length is checked before the app runs (the server holds the client to it). A
    streamed (chunked) body is read and counted here, up to the limit, and then replayed to the
    app; reading inside the app would be too late, since FastAPI turns any error while reading the
    body into a 400. FastAPI has no body limit of its own.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None:
            if declared > self.max_bytes:
                await self._reject(scope, send, f"the request body of {declared} bytes")
                return
            await self.app(scope, receive, send)
            return
        chunks: list[bytes] = []
        received = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # client went away
                return
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > self.max_bytes:
                await self._reject(scope, send, "the streamed request body")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _reject(self, scope: Scope, send: Send, what: str) -> None:
        problem = PayloadTooLargeError(
            f"{what} exceeds the limit of {self.max_bytes} bytes"
        ).problem(instance=scope.get("path"))
        body = json.dumps(problem.model_dump(mode="json", exclude_none=True)).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", PROBLEM_JSON.encode()),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


def freeze_heap() -> int:
    """Collect garbage once, then exempt everything alive from later collections; how many
    objects that froze.

    A service's start-up leaves a large heap that lives as long as the process (FastAPI,
    pydantic, numpy, the model or scene). Python's oldest-generation collections walk all of it:
    45-100 ms each, measured in the controller and the services, at unpredictable points of a
    search. Frozen, it is never walked again, and requests only pay for what they allocate.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


async def single_query_values(request: Request) -> None:
    """Refuse a query parameter given more than once (422 naming it): FastAPI would silently
    take the last value of a parameter declared once. A dependency of every route."""
    seen: set[str] = set()
    twice: list[str] = []
    for name, _ in request.query_params.multi_items():
        if name in seen and name not in twice:
            twice.append(name)
        seen.add(name)
    if twice:
        raise RequestValidationError(
            [
                {"loc": ("query", name), "msg": f"'{name}' is given twice", "type": "repeated"}
                for name in twice
            ]
        )


Readiness = Callable[[FastAPI], Awaitable[Sequence[str]]]
"""Why a started app cannot serve yet (nothing when it can), in words for its operators."""


class Probe(FrozenModel):
    """``GET /livez`` and ``GET /readyz`` when the answer is yes."""

    status: Literal["ok"]
    service: str


def _probes(name: str, readiness: Readiness | None) -> APIRouter:
    probes = APIRouter(tags=["probes"])

    @probes.get("/livez", response_model=Probe)
    async def livez() -> Probe:
        """Liveness: the process answers (an orchestrator restarts it when it stops)."""
        return Probe(status="ok", service=name)

    @probes.get("/readyz", response_model=Probe, responses=problem_responses(503))
    async def readyz(request: Request) -> Probe:
        """Readiness: the service can serve requests now; 503 with the reasons when it
        cannot (starting, stopping, or missing what it needs)."""
        app = request.app
        if not getattr(app.state, "serving", False):
            reasons: Sequence[str] = ["starting or stopping"]
        else:
            try:
                reasons = [] if readiness is None else await readiness(app)
            except Exception:  # a failing check is a "no", never a 500
                _log.exception("the readiness check of %s failed", name)
                reasons = ["the readiness check failed; see the service's log"]
        if reasons:
            raise ServiceUnavailableError(
                "; ".join(reasons),
                slug="not-ready",
                title="Not ready",
                extra={"reasons": list(reasons)},
            )
        return Probe(status="ok", service=name)

    return probes


def service_app(
    name: str,
    summary: str,
    lifespan: Callable[[FastAPI], AbstractAsyncContextManager[None]],
    router: APIRouter,
    max_body_bytes: int,
    *,
    settings: ServiceTokenSettings,
    guarded: bool,
    readiness: Readiness | None,
) -> FastAPI:
    """A COSMOS service app: its routes, the probes (``/livez``; ``/readyz``, which asks
    ``readiness`` once the lifespan has started, or, None, answers yes then), problem+json
    errors, a request body limit, and no query parameter given twice.

    A ``guarded`` app (a stage) serves only callers with the service token of ``settings``,
    except on the health and probe routes; any app refuses to start without a token unless
    ``COSMOS_SERVICE_AUTH=off`` (the controller needs it to call the stages).
    """

    @asynccontextmanager
    async def started(app: FastAPI) -> AsyncIterator[None]:
        try:
            settings.token()
        except MissingServiceTokenError as exc:
            _log.error("%s", exc)  # before uvicorn's traceback: the line that says what to do
            raise
        if guarded and settings.service_auth == "off":
            _log.warning("COSMOS_SERVICE_AUTH=off: this %s serves every caller", name)
        async with lifespan(app):
            freeze_heap()
            app.state.serving = True
            try:
                yield
            finally:
                app.state.serving = False
                gc.unfreeze()  # what the app leaves behind can be collected again

    app = FastAPI(
        title=f"COSMOS {name}",
        version="0.1.0",
        summary=summary,
        lifespan=started,
        dependencies=[Depends(single_query_values)],
    )
    install_problem_handlers(app)
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=max_body_bytes)
    if guarded and settings.service_auth == "token":
        # Added last, so it runs first: a stranger's body is never read. Without a token the
        # app does not start (above); until then the middleware refuses everyone.
        secret = settings.service_token
        app.add_middleware(
            ServiceTokenMiddleware, token=secret.get_secret_value() if secret else None
        )
        declare_service_token(app, lambda: problem_responses(401)[401])
    # Any route answers 422 for a query parameter given twice, and FastAPI's own 422s are
    # problem+json here, not its HTTPValidationError: declared once for all.
    app.include_router(_probes(name, readiness), responses=problem_responses(422))
    app.include_router(router, responses=problem_responses(422))
    publish_plain_schema(app)  # tuples as every OpenAPI tool reads them
    return app


def app_state(attribute: str) -> Callable[[Request], Awaitable[Any]]:
    """A route dependency giving ``app.state.<attribute>`` (what the lifespan built).

    Async on purpose: FastAPI runs a plain ``def`` dependency on its thread pool, a thread
    round trip (~0.3-0.6 ms) on every request for one attribute lookup.
    """

    async def state_of(request: Request) -> Any:
        return getattr(request.app.state, attribute)

    return state_of
