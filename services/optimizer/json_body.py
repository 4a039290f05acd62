"""A route's JSON body validated by pydantic-core straight from its bytes, answered and documented
as FastAPI answers and documents a body parameter.

A body parameter makes FastAPI ``json.loads`` the body into Python objects and validate those:
for a ``/next-pose`` request of 40 views (36 kB) that is about twice what
``model_validate_json`` on the raw bytes costs, and it grows with every view a search resends
(``python -m benchmarks.history``). A route that takes the :class:`~starlette.requests.Request`
instead reads the body with :func:`read_json` and documents it with :func:`json_request_body`.

The fast path only takes bodies FastAPI would have taken: a JSON media type, valid JSON, a valid
model. Anything else is read again exactly as FastAPI reads a body parameter (media type test,
``json.loads``, Python-mode validation, errors located under ``body``), so every refusal is the
one FastAPI gave (same status, fields and messages) and so is every acceptance.
"""

from __future__ import annotations

import email.message
import json
from typing import Any, TypeVar

from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException
from starlette.requests import Request

__all__ = ["json_request_body", "parse_json", "read_json"]

M = TypeVar("M", bound=BaseModel)


def _is_json(content_type: str | None) -> bool:
    """Whether FastAPI reads a body of this media type as JSON (``application/json`` or
    ``application/*+json``; a body without a media type is not, FastAPI's strict default)."""
    if not content_type:
        return False
    if content_type == "application/json":
        return True
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


def _as_fastapi_reads(body: bytes, content_type: str | None, model: type[M]) -> M:
    """``body`` read as FastAPI reads a body parameter of type ``model``: its model, or its
    :class:`RequestValidationError` (answered 422) or 400."""
    if not body:
        missing = {"type": "missing", "loc": ("body",), "msg": "Field required", "input": None}
        raise RequestValidationError([missing])
    value: Any = body  # a body that is not JSON is validated as bytes, and refused
    if _is_json(content_type):
        try:
            value = json.loads(body)
        except json.JSONDecodeError as exc:
            error = {
                "type": "json_invalid",
                "loc": ("body", exc.pos),
                "msg": "JSON decode error",
                "input": {},
                "ctx": {"error": exc.msg},
            }
            raise RequestValidationError([error], body=exc.doc) from exc
        except (ValueError, RecursionError) as exc:  # not UTF-8/16/32, or nested too deep
            raise HTTPException(400, "There was an error parsing the body") from exc
    try:
        return model.model_validate(value, from_attributes=True)
    except ValidationError as exc:
        errors = [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]
        raise RequestValidationError(errors, body=value) from exc


def parse_json(body: bytes, content_type: str | None, model: type[M]) -> M:
    """``body`` as a ``model``, validated from the bytes (module docstring).

    Raises
    ------
    RequestValidationError
        The body is empty, not JSON or not a valid ``model`` (FastAPI's errors, answered 422).
    HTTPException
        400: the body is JSON in no encoding JSON allows.
    """
    if body and _is_json(content_type):
        try:
            return model.model_validate_json(body)
        except ValidationError:
            pass  # refused as FastAPI refuses it, below; a refusal may take longer
    return _as_fastapi_reads(body, content_type, model)


async def read_json(request: Request, model: type[M]) -> M:
    """The request's body as a ``model`` (:func:`parse_json`)."""
    return parse_json(await request.body(), request.headers.get("content-type"), model)


def _inline(node: Any, defs: dict[str, Any], seen: tuple[str, ...] = ()) -> Any:
    """``node`` with every ``{"$ref": "#/$defs/X", ...}`` replaced by ``X``'s schema and the
    reference's own keywords (a default, a description)."""
    if isinstance(node, list):
        return [_inline(item, defs, seen) for item in node]
    if not isinstance(node, dict):
        return node
    ref = node.get("$ref")
    if isinstance(ref, str) and ref.startswith("#/$defs/"):
        name = ref.removeprefix("#/$defs/")
        if name in seen:
            raise ValueError(f"{name} refers to itself; a recursive model cannot be inlined")
        target = _inline(defs[name], defs, (*seen, name))
        return {**target, **{k: _inline(v, defs, seen) for k, v in node.items() if k != "$ref"}}
    return {key: _inline(value, defs, seen) for key, value in node.items()}


def json_request_body(model: type[BaseModel]) -> dict[str, Any]:
    """The OpenAPI ``requestBody`` of a route that reads a ``model`` with :func:`read_json`.

    The schema is the model's validation schema with its definitions inlined: a route's
    ``openapi_extra`` cannot add components, so the nested models cannot be references.
    """
    schema = model.model_json_schema(mode="validation")
    defs = schema.pop("$defs", {})
    return {
        "required": True,
        "content": {"application/json": {"schema": _inline(schema, defs)}},
    }
