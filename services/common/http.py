"""HTTP plumbing shared by the services: problem+json handlers, request body bounds
(:mod:`services.common.bodies`), the service token (:mod:`services.common.auth`) and the
liveness and readiness probes.

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
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from services.common.auth import (
    MissingServiceTokenError,
    ServiceTokenMiddleware,
    ServiceTokenSettings,
    declare_service_token,
)
from services.common.base import FrozenModel
from services.common.bodies import BodyLimits, BodyMiddleware
from services.common.errors import (
    ProblemDetails,
    ServiceError,
    ServiceUnavailableError,
    StartupError,
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
    body_limits: int | BodyLimits,
    *,
    settings: ServiceTokenSettings,
    guarded: bool,
    readiness: Readiness | None,
) -> FastAPI:
    """A COSMOS service app: its routes, the probes (``/livez``; ``/readyz``, which asks
    ``readiness`` once the lifespan has started, or, None, answers yes then), problem+json
    errors, request bodies bounded (``body_limits``: a size limit in bytes, with the default
    deadline and no budget, or :class:`~services.common.bodies.BodyLimits`), and no query
    parameter given twice.

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
        try:
            async with lifespan(app):
                freeze_heap()
                app.state.serving = True
                try:
                    yield
                finally:
                    app.state.serving = False
                    gc.unfreeze()  # what the app leaves behind can be collected again
        except StartupError as exc:
            _log.error("%s", exc)  # all an operator needs; the server drops the traceback
            raise

    app = FastAPI(
        title=f"COSMOS {name}",
        version="0.1.0",
        summary=summary,
        lifespan=started,
        dependencies=[Depends(single_query_values)],
    )
    install_problem_handlers(app)
    limits = body_limits if isinstance(body_limits, BodyLimits) else BodyLimits(body_limits)
    app.add_middleware(BodyMiddleware, limits=limits)
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
