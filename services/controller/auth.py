"""The controller's API key check, once for the routes and once before a request body is read.

:func:`authenticate` is the check: ``Authorization: Bearer <key>`` must carry a key of the
:class:`~services.controller.keys.KeyStore`, not revoked, else :class:`UnauthorizedError` (401
problem details with ``WWW-Authenticate: Bearer``). The routes (:mod:`services.controller.api`)
call it through their :data:`Caller` dependency; :func:`needs_key` tells which routes want a key.

:class:`ApiKeyMiddleware` calls it from the request's head, in front of the body bounds
(:class:`~services.common.bodies.BodyMiddleware`): a request with a body, to a route that wants a
key, is refused at once when its key is missing or wrong, before its body is admitted to the
budget of bytes in flight or read, so a stranger's upload costs neither (its connection is
closed, the body unread). A key it accepts is handed on in the scope (:func:`checked_key`), so
the route does not look it up again. Requests without a body go on to the route, whose check
answers the same.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Annotated, Final

from fastapi import Depends, Request
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Receive, Scope, Send

from services.common.auth import PROBE_PATHS
from services.common.bodies import has_body, send_problem
from services.common.errors import ServiceUnavailableError, UnauthorizedError
from services.common.http import app_state
from services.controller.keys import ApiKey, KeyStore
from services.controller.wiring import Controller

__all__ = [
    "ApiKeyMiddleware",
    "Caller",
    "authenticate",
    "caller",
    "checked_key",
    "needs_key",
]

_SCOPE_KEY: Final = "cosmos.api_key"
"""Where :class:`ApiKeyMiddleware` leaves the key it accepted, in the request's scope."""


def _unauthorized(detail: str, challenge: str) -> UnauthorizedError:
    return UnauthorizedError(detail, headers={"WWW-Authenticate": challenge})


def authenticate(keys: KeyStore, authorization: str | None) -> ApiKey:
    """The key an ``Authorization`` header value carries (``Bearer <key>``, the scheme in any
    case), or :class:`UnauthorizedError` when there is none or it is unknown or revoked."""
    scheme, _, given = (authorization or "").strip().partition(" ")
    given = given.strip()
    if scheme.lower() != "bearer" or not given:
        raise _unauthorized(
            "send an API key as Authorization: Bearer <key>; `cosmos keys create` makes one "
            "(`cosmos up` prints a local one)",
            'Bearer realm="cosmos"',
        )
    key = keys.verify(given)
    if key is None:
        raise _unauthorized(
            "the API key is unknown or was revoked; ask for a new one (cosmos keys create)",
            'Bearer realm="cosmos", error="invalid_token"',
        )
    return key


def is_admin(keys: KeyStore, authorization: str | None) -> bool:
    """Whether an ``Authorization`` header value carries an admin key. Any other key, a wrong
    one or none is simply not an admin (no error): the open health answers them all."""
    if authorization is None:
        return False
    try:
        return authenticate(keys, authorization).admin
    except (UnauthorizedError, ServiceUnavailableError):  # a wrong key, or no database
        return False


def checked_key(scope: Scope) -> ApiKey | None:
    """The key :class:`ApiKeyMiddleware` accepted for this request (None: it did not check)."""
    key = scope.get(_SCOPE_KEY)
    return key if isinstance(key, ApiKey) else None


class ApiKeyMiddleware:
    """Refuse a request with a body to a route that wants a key (``needs_key(scope)``) with 401,
    before its body is read, unless its key passes :func:`authenticate` against
    ``keys(scope)``."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        needs_key: Callable[[Scope], bool],
        keys: Callable[[Scope], KeyStore],
    ) -> None:
        self.app = app
        self._needs_key = needs_key
        self._keys = keys

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not has_body(scope) or not self._needs_key(scope):
            await self.app(scope, receive, send)
            return
        given = next((v for k, v in scope["headers"] if k == b"authorization"), None)
        try:  # on a thread: a database that hangs holds this request, not the event loop
            key = await asyncio.to_thread(
                authenticate, self._keys(scope), None if given is None else given.decode("latin-1")
            )
        except (UnauthorizedError, ServiceUnavailableError) as exc:  # no key, or no database
            # The body is never kept: it is dropped as it comes, then the connection closed.
            problem = exc.problem(scope.get("path"))
            await send_problem(send, scope, problem, exc.headers, receive=receive)
            return
        scope[_SCOPE_KEY] = key
        await self.app(scope, receive, send)


_State = Annotated[Controller, Depends(app_state("controller"))]

_bearer = HTTPBearer(
    scheme_name="ApiKey",
    bearerFormat="cosmos_<43 characters>",
    description="An API key: `cosmos keys create` makes one (`cosmos up` prints a local one).",
    auto_error=False,
)


async def caller(
    request: Request,
    state: _State,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> ApiKey | None:
    """The key a request acts for; None when auth is off (everyone's searches, no quotas).
    ``credentials`` only declares the scheme in the OpenAPI schema: the check is
    :func:`authenticate`'s, done already for a request with a body."""
    if not state.settings.controller_auth:
        return None
    return checked_key(request.scope) or await asyncio.to_thread(
        authenticate, state.keys, request.headers.get("authorization")
    )


Caller = Annotated[ApiKey | None, Depends(caller)]


def _wants_key(route: BaseRoute) -> bool:
    """Whether ``route`` checks an API key (depends on :func:`caller`, directly or not)."""
    if not isinstance(route, APIRoute):
        return False  # not a FastAPI route: no dependencies, no key
    pending = [route.dependant]
    while pending:
        dependant = pending.pop()
        if dependant.call is caller:
            return True
        pending.extend(dependant.dependencies)
    return False


def needs_key(routes: Sequence[BaseRoute], scope: Scope) -> bool:
    """Whether a request to ``scope``'s path wants an API key before its body is read: the
    route of ``routes`` (the API's) that takes it checks one (its method aside, so a wrong
    method gets its 405 where the path is open), or no route takes the path at all (the probes
    and the OpenAPI documents are open)."""
    partial: BaseRoute | None = None
    for route in routes:  # in order, as the app dispatches
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
