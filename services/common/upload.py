"""An uploaded image: a ``multipart/form-data`` field ``image``, or the raw body.

Two ways in, one image out, for ``POST /detect`` and ``POST /searches``. A form (the file in the
field ``image``, any options as text fields) is what people and browsers send; a raw body with
the image's own media type (``image/png``, ``image/jpeg`` or ``image/x-portable-pixmap``), any
options in the query, is what programs send: no multipart to write or parse, ~1-1.5 ms less per
230 KB image on the 2-core bench machine (``cosmos bench --profile``). Either way the bytes are
only handed on here; what they hold is checked by :mod:`services.common.images`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException
from starlette.requests import Request

from services.common.errors import BadRequestError, UnprocessableError, UnsupportedMediaTypeError
from services.common.images import PPM_MEDIA_TYPE

__all__ = ["FIELD", "RAW_MEDIA_TYPES", "Upload", "read_upload", "request_body"]

FIELD: Final = "image"
RAW_MEDIA_TYPES: Final = ("image/png", "image/jpeg", PPM_MEDIA_TYPE)
MULTIPART: Final = "multipart/form-data"

_BINARY: Final[dict[str, Any]] = {"type": "string", "format": "binary"}


def request_body(
    fields: Mapping[str, dict[str, Any]] | None = None, required: tuple[str, ...] = ()
) -> dict[str, Any]:
    """The OpenAPI ``requestBody`` of a route taking an image: a form with the file in
    ``image`` and the text ``fields`` (JSON schemas), or the raw image bytes."""
    return {
        "required": True,
        "description": "The image: a form with the file in the field 'image', or the raw PNG, "
        "JPEG or binary PPM bytes with their media type.",
        "content": {
            MULTIPART: {
                "schema": {
                    "type": "object",
                    "required": [FIELD, *required],
                    "properties": {
                        FIELD: {**_BINARY, "description": "The image: PNG, JPEG or binary PPM."},
                        **(fields or {}),
                    },
                }
            },
            **{media_type: {"schema": _BINARY} for media_type in RAW_MEDIA_TYPES},
        },
    }


@dataclass(frozen=True)
class Upload:
    """The image's bytes and, from a form, its text fields (empty for a raw body)."""

    image: bytes
    fields: Mapping[str, str] = field(default_factory=dict)


def _media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";", 1)[0].strip().lower()


async def read_upload(request: Request) -> Upload:
    """The uploaded image (and a form's text fields).

    Raises
    ------
    UnsupportedMediaTypeError
        The body is neither a form nor one of :data:`RAW_MEDIA_TYPES` (field ``content-type``).
    BadRequestError
        The form is not valid ``multipart/form-data`` (field ``body``).
    UnprocessableError
        The form has no file in the field ``image`` (field ``image``), or gives a text field
        twice (that field).
    """
    media_type = _media_type(request)
    if media_type in RAW_MEDIA_TYPES:
        return Upload(await request.body())
    route = f"{request.method} {request.url.path}"
    if media_type != MULTIPART:
        raise UnsupportedMediaTypeError(
            f"{route} takes multipart/form-data with the image in the field '{FIELD}', or "
            f"the image itself as {', '.join(RAW_MEDIA_TYPES)}; not "
            f"{media_type or 'a body without a content type'}",
            field="content-type",
        )
    try:
        async with request.form(max_files=4, max_fields=16) as form:
            upload = form.get(FIELD)
            if not isinstance(upload, UploadFile):
                what = "a text field" if upload is not None else "missing"
                raise UnprocessableError(
                    f"the form's field '{FIELD}' must be a file (it is {what})", field=FIELD
                )
            fields: dict[str, str] = {}
            for name, value in form.multi_items():
                if isinstance(value, str):
                    if name in fields:
                        raise UnprocessableError(f"the form gives '{name}' twice", field=name)
                    fields[name] = value
            return Upload(await upload.read(), fields)
    except HTTPException as exc:  # how Starlette reports a malformed form inside an app
        raise BadRequestError(
            f"the multipart body is malformed: {exc.detail}", field="body"
        ) from exc
