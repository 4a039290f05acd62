"""Domain errors that map to RFC 9457 problem details, shared by every service.

Domain code raises these; each app's handler (:mod:`services.common.http`) turns them into
``application/problem+json`` responses. ``type`` is a URN naming the kind of problem.
"""

from __future__ import annotations

from typing import Any

from pydantic import ConfigDict

from services.common.base import FrozenModel

__all__ = [
    "BadRequestError",
    "ConflictError",
    "NotFoundError",
    "PayloadTooLargeError",
    "ProblemDetails",
    "ServiceError",
    "ServiceUnavailableError",
    "StartupError",
    "TooManyRequestsError",
    "UnauthorizedError",
    "UnprocessableError",
    "UnsupportedMediaTypeError",
    "problem_type",
]


def problem_type(slug: str) -> str:
    """The ``type`` URI of a problem kind."""
    return f"urn:cosmos:problem:{slug}"


class ProblemDetails(FrozenModel):
    """An RFC 9457 problem details object, with COSMOS extensions (``field``, ``errors``)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    type: str = "about:blank"
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    field: str | None = None
    errors: list[dict[str, Any]] | None = None


class ServiceError(Exception):
    """Base of every error a service answers with a problem+json body."""

    status: int = 500
    slug: str = "internal-error"
    title: str = "Internal error"

    def __init__(
        self,
        detail: str,
        *,
        field: str | None = None,
        slug: str | None = None,
        title: str | None = None,
        extra: dict[str, Any] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.detail = detail
        self.field = field
        self.headers = headers or {}
        """Response headers the problem needs (``WWW-Authenticate``, ``Retry-After``)."""
        if slug is not None:
            self.slug = slug
        if title is not None:
            self.title = title
        self.extra = extra or {}

    def problem(self, instance: str | None = None) -> ProblemDetails:
        """This error as a problem details object."""
        return ProblemDetails(
            type=problem_type(self.slug),
            title=self.title,
            status=self.status,
            detail=self.detail,
            instance=instance,
            field=self.field,
            **self.extra,
        )


class BadRequestError(ServiceError):
    status = 400
    slug = "bad-request"
    title = "Bad request"


class UnauthorizedError(ServiceError):
    """No credentials, or ones the service does not accept; answers ``WWW-Authenticate``."""

    status = 401
    slug = "unauthorized"
    title = "Unauthorized"


class NotFoundError(ServiceError):
    status = 404
    slug = "not-found"
    title = "Not found"


class ConflictError(ServiceError):
    status = 409
    slug = "conflict"
    title = "Conflict"


class PayloadTooLargeError(ServiceError):
    status = 413
    slug = "payload-too-large"
    title = "Payload too large"


class UnsupportedMediaTypeError(ServiceError):
    status = 415
    slug = "unsupported-media-type"
    title = "Unsupported media type"


class UnprocessableError(ServiceError):
    status = 422
    slug = "invalid-request"
    title = "Invalid request"


class TooManyRequestsError(ServiceError):
    """A limit of the caller's was reached; answers ``Retry-After``."""

    status = 429
    slug = "too-many-requests"
    title = "Too many requests"


class ServiceUnavailableError(ServiceError):
    status = 503
    slug = "unavailable"
    title = "Service unavailable"


class StartupError(Exception):
    """A service cannot start: its message, one line naming the setting to change, is all an
    operator needs (the server logs it without a traceback)."""
