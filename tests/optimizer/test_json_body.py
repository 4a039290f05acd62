"""A body read from its raw bytes (:mod:`services.optimizer.json_body`) is answered and
documented as FastAPI answers and documents a body parameter of the same model."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Any

import httpx
import pytest
from fastapi import FastAPI, Request, Response
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from services.common.contracts.optimize import NextPoseRequest
from services.common.http import install_problem_handlers
from services.common.openapi import plain_tuples
from services.optimizer.app import create_app
from services.optimizer.json_body import json_request_body, read_json

pytestmark = pytest.mark.anyio

VALID: dict[str, Any] = {
    "scene": "demo",
    "strategy": "simple",
    "target": {
        "image_size": [320, 240],
        "detections": [
            {"label": "sphere", "class_id": 0, "confidence": 0.9, "box": [10, 20, 30, 40]},
            {
                "label": "cube",
                "class_id": 1,
                "confidence": 0.5,
                "box": [50.5, 60, 70, 80.25],
                "color": [200, 10, 10],
            },
        ],
    },
    "history": [
        {"pose": {"lat": 1, "lon": 2}, "image_size": [320, 240], "detections": []},
        {"pose": {"theta_deg": 30.0, "phi_deg": 15}, "image_size": [640, 480]},
    ],
    "tolerances": {"match_rms_px": 2},
}

MEDIA_TYPES = (
    "application/json",
    "application/json; charset=utf-8",
    "application/problem+json",
    "text/plain",
    "application/x-www-form-urlencoded",
    None,
)

BODIES = (
    b"",
    b" ",
    b"{",
    b"[]",
    b"null",
    b"1",
    b'"text"',
    b"{}",
    b'{"target": NaN}',
    b'{"target": {}}',
    b'{"target": 1, "target": {"image_size": [1, 1], "detections": []}}',
    b'{"a": "\xc3\x28"}',  # not UTF-8
    b"\xff\xfe{\x00}\x00",  # UTF-16
    b'{"target": "\\ud800"}',  # a lone surrogate
    b"[" * 100_000,  # nested too deep
    json.dumps(VALID).encode(),
    json.dumps(VALID).encode() + b" \n",
    json.dumps(VALID).encode() + b"x",
    json.dumps({**VALID, "extra": 1}).encode(),
    json.dumps({**VALID, "strategy": None}).encode(),
    json.dumps({**VALID, "tolerances": {"match_rms_px": "2.5"}}).encode(),
    json.dumps(
        {**VALID, "history": [{"pose": {"lat": "1", "lon": 2.0}, "image_size": [1, 1]}]}
    ).encode(),
    json.dumps({**VALID, "history": [{"pose": {"lat": 1}, "image_size": [0, 1]}] * 3}).encode(),
    json.dumps(
        {**VALID, "history": [{"pose": {"lat": True, "lon": 1}, "image_size": [1, 1]}]}
    ).encode(),
)


def _app(raw: bool) -> FastAPI:
    """One route answering the body it validated: read raw, or as FastAPI's body parameter."""
    app = FastAPI()
    install_problem_handlers(app)
    if raw:

        @app.post("/next-pose", openapi_extra={"requestBody": json_request_body(NextPoseRequest)})
        async def read(request: Request) -> Response:
            body = await read_json(request, NextPoseRequest)
            return Response(body.model_dump_json(), media_type="application/json")

    else:

        @app.post("/next-pose")
        async def parameter(body: NextPoseRequest) -> Response:
            return Response(body.model_dump_json(), media_type="application/json")

    return app


Clients = tuple[httpx.AsyncClient, httpx.AsyncClient]


@pytest.fixture(scope="module")
async def clients() -> AsyncIterator[Clients]:
    def client(app: FastAPI) -> httpx.AsyncClient:
        return httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://o")

    async with client(_app(raw=True)) as raw, client(_app(raw=False)) as parameter:
        yield raw, parameter


async def answers(
    clients: Clients, body: bytes, media_type: str | None
) -> tuple[tuple[int, str | None, bytes], tuple[int, str | None, bytes]]:
    headers = {} if media_type is None else {"content-type": media_type}
    got = [await c.post("/next-pose", content=body, headers=headers) for c in clients]
    raw, parameter = ((r.status_code, r.headers.get("content-type"), r.content) for r in got)
    return raw, parameter


@pytest.mark.parametrize("media_type", MEDIA_TYPES)
@pytest.mark.parametrize("body", BODIES, ids=range(len(BODIES)))
async def test_every_body_is_answered_as_by_a_body_parameter(clients, body, media_type):
    raw, parameter = await answers(clients, body, media_type)
    assert raw == parameter
    if body.startswith(json.dumps(VALID).encode()) and body.strip().endswith(b"}"):
        assert raw[0] == (200 if media_type in MEDIA_TYPES[:3] else 422)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    value=st.fixed_dictionaries(
        {}, optional={**dict.fromkeys(VALID, json_values), "x": json_values}
    )
    | json_values,
    tail=st.sampled_from([b"", b" ", b"}"]),
)
async def test_any_json_is_answered_as_by_a_body_parameter(clients, value, tail):
    body = json.dumps(value).encode() + tail
    raw, parameter = await answers(clients, body, "application/json")
    assert raw == parameter


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    fields=st.fixed_dictionaries(
        {}, optional={k: st.sampled_from([VALID[k], None, 0, [], {}]) for k in VALID}
    )
)
async def test_requests_near_a_valid_one_are_answered_as_by_a_body_parameter(clients, fields):
    raw, parameter = await answers(clients, json.dumps(fields).encode(), "application/json")
    assert raw == parameter


def _resolved(node: Any, components: dict[str, Any]) -> Any:
    """``node`` with every ``#/components/schemas/X`` reference replaced by ``X``."""
    if isinstance(node, list):
        return [_resolved(item, components) for item in node]
    if not isinstance(node, dict):
        return node
    ref = node.get("$ref")
    if isinstance(ref, str):
        name = ref.removeprefix("#/components/schemas/")
        rest = {k: _resolved(v, components) for k, v in node.items() if k != "$ref"}
        return {**_resolved(components[name], components), **rest}
    return {k: _resolved(v, components) for k, v in node.items()}


def test_the_service_documents_the_body_as_a_body_parameter_would():
    def request_body(app: FastAPI) -> Any:
        document = app.openapi()
        body = document["paths"]["/next-pose"]["post"]["requestBody"]
        return _resolved(body, document.get("components", {}).get("schemas", {}))

    documented = request_body(create_app())
    # every service publishes tuples plainly (services.common.openapi); a bare app does not
    assert documented == plain_tuples(request_body(_app(raw=False)))
    assert "$ref" not in json.dumps(documented)
    assert documented["required"] is True
    schema = documented["content"]["application/json"]["schema"]
    assert schema["required"] == ["target"]
    assert schema["properties"]["history"]["items"]["properties"]["pose"]["title"] == "PoseQuery"


class Node(BaseModel):
    children: list[Node] = []


def test_a_recursive_model_cannot_be_inlined():
    with pytest.raises(ValueError, match="refers to itself"):
        json_request_body(Node)
