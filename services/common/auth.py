"""The service token: the stages (renderer, detector, optimizer) serve only callers that hold it.

One secret, ``COSMOS_SERVICE_TOKEN``, is given to every service of a stack: the stages require it
as ``Authorization: Bearer <token>`` on every route but the health probes (:data:`PROBE_PATHS`),
and the controller sends it on every stage call. ``cosmos up`` and ``cosmos demo`` make one per
run. A service without a token refuses to start, unless ``COSMOS_SERVICE_AUTH=off`` says that
every caller is welcome (development on a trusted machine).

The check is a pure ASGI middleware (:class:`ServiceTokenMiddleware`), in front of everything
else, so a stranger's request is refused before its body is read and whatever its path (the API
docs too, and paths that do not exist); :func:`declare_service_token` writes the same rule into
the OpenAPI schema.
"""

from __future__ import annotations

import hmac
import logging
import os
import secrets
from collections.abc import Callable, Mapping
from typing import Any, Literal

from fastapi import FastAPI
from pydantic import SecretStr, field_validator
from starlette.types import ASGIApp, Receive, Scope, Send

from services.common.bodies import send_problem
from services.common.errors import ProblemDetails, problem_type
from services.common.settings import ServiceSettings

__all__ = [
    "MIN_TOKEN_CHARS",
    "PROBE_PATHS",
    "SCHEME_NAME",
    "TOKEN_VARIABLE",
    "MissingServiceTokenError",
    "ServiceTokenMiddleware",
    "ServiceTokenSettings",
    "bearer",
    "declare_service_token",
    "new_token",
    "token_from_environment",
]

TOKEN_VARIABLE = "COSMOS_SERVICE_TOKEN"
PROBE_PATHS = frozenset({"/health", "/livez", "/readyz"})
"""The routes anyone may call: health and the probes of orchestrators and load balancers."""
SCHEME_NAME = "serviceToken"
MIN_TOKEN_CHARS = 16

_log = logging.getLogger("cosmos.auth")
_HOW_TO_SET = (
    f"give every service of the stack the same {TOKEN_VARIABLE}, e.g. "
    f"{TOKEN_VARIABLE}=$(python -c 'import secrets; print(secrets.token_urlsafe(32))')"
)


def new_token() -> str:
    """A fresh random token (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def bearer(token: str | None) -> dict[str, str]:
    """The request header that carries ``token`` (none without a token)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


def token_from_environment(environ: Mapping[str, str] | None = None) -> str | None:
    """``COSMOS_SERVICE_TOKEN`` of this process (the CLI's clients of a stage send it)."""
    return (os.environ if environ is None else environ).get(TOKEN_VARIABLE) or None


class MissingServiceTokenError(RuntimeError):
    """A service was started without a token and without ``COSMOS_SERVICE_AUTH=off``."""


class ServiceTokenSettings(ServiceSettings):
    """The service token, the same for every service of a stack: what the stages require and
    the controller sends. ``service_auth="off"`` lets the stages serve anyone (development)."""

    service_token: SecretStr | None = None
    """The stack's shared secret, at least 16 characters (:data:`MIN_TOKEN_CHARS`): the stages
    serve only requests that carry it, and the controller sends it on every stage call."""
    service_auth: Literal["token", "off"] = "token"
    """``off``: the stages ask no token of their callers."""

    @field_validator("service_token")
    @classmethod
    def _long_enough(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None or not value.get_secret_value():
            return None  # an empty variable is an unset one
        if len(value.get_secret_value()) < MIN_TOKEN_CHARS:
            raise ValueError(
                f"{TOKEN_VARIABLE} is shorter than {MIN_TOKEN_CHARS} characters; {_HOW_TO_SET}"
            )
        return value

    def token(self) -> str | None:
        """The token, or None when ``COSMOS_SERVICE_AUTH=off``; raises
        :class:`MissingServiceTokenError` when there is none to use (at start-up)."""
        if self.service_token is not None:
            return self.service_token.get_secret_value()
        if self.service_auth == "off":
            return None
        raise MissingServiceTokenError(
            f"{TOKEN_VARIABLE} is not set, and the renderer, detector and optimizer serve only "
            f"callers that send it (the controller does). `cosmos up` and `cosmos demo` make "
            f"one per run; for services started otherwise, {_HOW_TO_SET}. For development on a "
            f"trusted machine only, COSMOS_SERVICE_AUTH=off serves every caller without one."
        )


class ServiceTokenMiddleware:
    """Answer 401 (problem+json) to an HTTP request without ``Authorization: Bearer <token>``,
    except on :data:`PROBE_PATHS`. The token is compared in constant time. Without a token
    (None) every request but the probes' is refused."""

    def __init__(self, app: ASGIApp, token: str | None) -> None:
        self.app = app
        self._expected = f"Bearer {token}".encode() if token else None
        self._scheme = b"bearer "

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in PROBE_PATHS:
            await self.app(scope, receive, send)
            return
        given = next((v for k, v in scope["headers"] if k == b"authorization"), None)
        if given is None or given[:7].lower() != self._scheme:
            detail = "this service needs the stack's service token: Authorization: Bearer <token>"
        elif self._expected is not None and hmac.compare_digest(
            b"Bearer " + given[7:],
            self._expected,  # the scheme is case-insensitive (RFC 9110)
        ):
            await self.app(scope, receive, send)
            return
        else:
            detail = "the service token is wrong"
        problem = ProblemDetails(
            type=problem_type("unauthorized"),
            title="Unauthorized",
            status=401,
            detail=detail,
            instance=scope["path"],
        )
        # A body is not kept: it is dropped as it comes, then the connection closed (bodies.py).
        challenge = {"WWW-Authenticate": 'Bearer realm="cosmos"'}
        await send_problem(send, scope, problem, challenge, receive=receive)


def declare_service_token(app: FastAPI, problem: Callable[[], dict[str, Any]]) -> None:
    """Say in ``app``'s OpenAPI schema what :class:`ServiceTokenMiddleware` does: a bearer
    security scheme, required by (and a 401 ``problem()`` answer on) every operation but the
    probes'."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        schemes = schema.setdefault("components", {}).setdefault("securitySchemes", {})
        schemes[SCHEME_NAME] = {
            "type": "http",
            "scheme": "bearer",
            "description": f"The stack's service token ({TOKEN_VARIABLE}).",
        }
        for path, operations in schema.get("paths", {}).items():
            if path in PROBE_PATHS:
                continue
            for operation in operations.values():
                operation["security"] = [{SCHEME_NAME: []}]
                operation.setdefault("responses", {}).setdefault("401", problem())
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
