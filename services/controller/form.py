"""What ``POST /searches`` was given besides the image, and how its OpenAPI schema says so.

The options (:class:`~services.common.contracts.search.SearchOptions`) come as the form's text
fields beside the file ``image``, or as query parameters beside a raw image body (what the bench and
:class:`~services.controller.client.ControllerClient` send: no multipart to write or parse, and
a search's start view begins rendering ~2 ms sooner). Invalid options answer 422 like any
FastAPI parameter would, naming the field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Final

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.common.contracts.free import CameraAttitude, PhotoIntrinsics
from services.common.contracts.search import SearchOptions
from services.common.errors import UnprocessableError
from services.common.geometry.free_camera import LensDistortion
from services.common.upload import request_body

__all__ = ["OPENAPI", "photo_attitude", "photo_intrinsics", "search_options"]


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


def _finite(text: str, field: str) -> list[float]:
    values = [float(part) for part in text.split(",")]  # the option's pattern: numbers
    if not all(math.isfinite(v) for v in values):
        raise UnprocessableError(f"{field} must be finite numbers", field=field)
    return values


def _four(text: str, field: str) -> tuple[float, float, float, float]:
    values = _finite(text, field)  # the option's pattern: four numbers
    return values[0], values[1], values[2], values[3]


def photo_intrinsics(options: SearchOptions) -> PhotoIntrinsics | None:
    """The photo's intrinsics a free search was given (``fov_deg`` or ``intrinsics``
    ``fx,fy,cx,cy``, and ``distortion`` ``k1,k2,p1,p2[,k3]``), None when none were. Raises
    :class:`UnprocessableError` naming the field for intrinsics of a hemisphere search, both
    ``fov_deg`` and ``intrinsics``, a distortion without either, or values out of range."""
    given = {
        name: value
        for name, value in (
            ("fov_deg", options.fov_deg),
            ("intrinsics", options.intrinsics),
            ("distortion", options.distortion),
        )
        if value is not None
    }
    if not given:
        return None
    if options.mode != "free":
        field = next(iter(given))
        raise UnprocessableError(f"{field} is for a free search (mode=free)", field=field)
    if options.fov_deg is not None and options.intrinsics is not None:
        raise UnprocessableError("give fov_deg or intrinsics, not both", field="intrinsics")
    if options.fov_deg is None and options.intrinsics is None:
        raise UnprocessableError(
            "distortion needs the focal length: give fov_deg or intrinsics too",
            field="distortion",
        )
    fields: dict[str, object] = {"fov_deg": options.fov_deg}
    if options.intrinsics is not None:
        fx, fy, cx, cy = _four(options.intrinsics, "intrinsics")
        fields = {"fx_px": fx, "fy_px": fy, "cx_px": cx, "cy_px": cy}
    name = "intrinsics"
    try:
        if options.distortion is not None:
            name = "distortion"
            fields["distortion"] = LensDistortion.of_coefficients(
                _finite(options.distortion, "distortion")
            )
            name = "intrinsics" if options.intrinsics is not None else "fov_deg"
        return PhotoIntrinsics.model_validate(fields)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        raise UnprocessableError(f"{name}: {first['msg']}", field=name) from exc


def photo_attitude(options: SearchOptions) -> CameraAttitude | None:
    """The camera's pitch and roll a free search was given (``attitude`` ``pitch,roll``), None
    when not. Raises :class:`UnprocessableError` naming the field for an attitude on a
    hemisphere search, or angles out of range (pitch within ±90°, roll within ±180°)."""
    if options.attitude is None:
        return None
    if options.mode != "free":
        raise UnprocessableError("attitude is for a free search (mode=free)", field="attitude")
    pitch, roll = _finite(options.attitude, "attitude")
    try:
        return CameraAttitude(pitch_deg=pitch, roll_deg=roll)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        where = ".".join(str(part) for part in first["loc"])
        raise UnprocessableError(f"attitude: {where} {first['msg']}", field="attitude") from exc
