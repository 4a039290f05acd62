"""What ``POST /searches`` was given besides the image, and how its OpenAPI schema says so.

The options (:class:`~services.common.contracts.search.SearchOptions`) come as the form's text
fields beside the file ``image``, or as query parameters beside a raw image body (what the bench and
:class:`~services.controller.client.ControllerClient` send: no multipart to write or parse, and
a search's start view begins rendering ~2 ms sooner). Invalid options answer 422 like any
FastAPI parameter would, naming the field.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Final

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.common.contracts.search import SearchOptions
from services.common.upload import request_body

__all__ = ["OPENAPI", "search_options"]


def _plain(schema: dict[str, Any]) -> dict[str, Any]:
    """An optional field's schema without its ``null`` branch (a parameter is just left out)."""
    branches = [b for b in schema.get("anyOf", ()) if b.get("type") != "null"]
    if len(branches) == 1:
        rest = {k: v for k, v in schema.items() if k not in ("anyOf", "default")}
        return {**branches[0], **rest}
    return {k: v for k, v in schema.items() if k != "default"}


def _openapi() -> dict[str, Any]:
    schema = SearchOptions.model_json_schema()
    defs = schema.get("$defs", {})
    if defs:  # inline schemas only: the route's extra OpenAPI has no components of its own
        raise RuntimeError(f"SearchOptions needs $defs {sorted(defs)}; inline them")
    fields = {name: _plain(field) for name, field in schema["properties"].items()}
    parameters = [
        {
            "name": name,
            "in": "query",
            "required": False,
            "description": f"With a raw image body: {field.get('description', name)}",
            "schema": {k: v for k, v in field.items() if k not in ("description", "title")},
        }
        for name, field in fields.items()
    ]
    return {
        "parameters": parameters,
        "requestBody": request_body(fields, required=tuple(schema.get("required", ()))),
    }


OPENAPI: Final = _openapi()
"""``openapi_extra`` of ``POST /searches``: the options as query parameters, the body."""


def search_options(form: Mapping[str, str], query: Sequence[tuple[str, str]]) -> SearchOptions:
    """The options from a form's text fields and the query (a name in both, or twice in the
    query, is refused); empty values count as not given, as for FastAPI's form fields.

    Raises
    ------
    RequestValidationError
        Answered 422 with each invalid field named.
    """
    given: dict[str, str] = {}
    where: dict[str, str] = {}
    errors: list[dict[str, Any]] = []
    for place, items in (("body", form.items()), ("query", query)):
        for name, value in items:
            if name in given:
                errors.append(
                    {"loc": (place, name), "msg": f"'{name}' is given twice", "type": "twice"}
                )
                continue
            given[name], where[name] = value, place
    if errors:
        raise RequestValidationError(errors)
    values = {name: value for name, value in given.items() if value != ""}
    try:
        return SearchOptions.model_validate(values)
    except ValidationError as exc:
        raise RequestValidationError(
            [
                {**err, "loc": (where.get(str(err["loc"][0]), "body"), *err["loc"])}
                if err["loc"]
                else err
                for err in exc.errors(include_url=False, include_context=False)
            ]
        ) from exc
