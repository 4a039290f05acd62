"""Test support: paths, real service processes (see :mod:`cosmos.launch`), and
schema-driven fuzzing of a running service."""

from __future__ import annotations

import os
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import schemathesis
from asgi_lifespan import LifespanManager
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import positive_data_acceptance
from starlette.types import ASGIApp

from cosmos.launch import ROOT, ServiceProcess, free_port, running_service
from cosmos.stack import Stack, local_stack
from services.common.auth import PROBE_PATHS, bearer, new_token

__all__ = [
    "ROOT",
    "ServiceProcess",
    "assert_token_required",
    "e2e_stack",
    "skip_unless_on_ci",
    "free_port",
    "fuzz_service",
    "running_service",
]


MODEL = ROOT / "models" / "detector.onnx"


@contextmanager
def e2e_stack(workdir: Path) -> Iterator[Stack]:
    """The four real services on loopback (:func:`~cosmos.stack.local_stack`) for end-to-end
    tests; fails at once without the shipped detector model."""
    if not MODEL.exists() and "COSMOS_DETECTOR_MODEL" not in os.environ:
        pytest.fail(f"the shipped detector model {MODEL} is missing")
    with local_stack(workdir) as running:
        yield running


def skip_unless_on_ci(why: str | None, tests: str) -> None:
    """Skip the ``tests`` (e.g. "the browser tests") for the reason ``why``, if there is one;
    on CI (``CI`` set), where they must run, fail instead."""
    if why is None:
        return
    if os.environ.get("CI"):
        pytest.fail(f"{tests} must run on CI: {why}")
    pytest.skip(why)


def assert_token_required(
    service: ServiceProcess,
    method: str,
    path: str,
    headers: dict[str, str] | None = None,
    **request: Any,
) -> None:
    """The stage process ``service`` answers ``method path`` (``headers`` and ``request``:
    httpx's arguments) with 401 problem details without its service token or with another, with
    200 with it; its health and probe routes answer anyone."""
    url = f"{service.url}{path}"
    for auth in ({}, bearer(new_token()), {"Authorization": service.token or ""}):
        sent = {**(headers or {}), **auth}
        refused = httpx.request(method, url, headers=sent, timeout=60.0, **request)
        assert refused.status_code == 401, (auth, refused.text)
        assert refused.headers["content-type"] == "application/problem+json"
        assert refused.headers["www-authenticate"].startswith("Bearer")
    sent = {**(headers or {}), **service.headers}
    served = httpx.request(method, url, headers=sent, timeout=60.0, **request)
    assert served.status_code == 200, served.text
    for probe in sorted(PROBE_PATHS):
        assert httpx.get(f"{service.url}{probe}", timeout=10.0).status_code == 200, probe


def fuzz_service(
    url: str,
    *,
    max_examples: int = 25,
    timeout_s: float = 60.0,
    headers: dict[str, str] | None = None,
) -> int:
    """Fuzz every operation of the service at ``url`` from its OpenAPI schema (schemathesis):
    valid and invalid inputs alike must never get a 5xx, and every answer must match the route's
    declared status codes, media types and schemas. Returns the number of operations.

    Schema-valid requests may still be refused with a 4xx problem (whether a pose is on a scene's
    grid, bytes are an image, a scene exists, depends on what a static schema cannot say), so the
    ``positive_data_acceptance`` heuristic is the one check left out. ``headers`` go with every
    request (an API key: schemathesis also checks that the routes refuse requests without it).
    """
    document = httpx.get(f"{url}/openapi.json", timeout=10.0, headers=headers).json()
    schema = schemathesis.openapi.from_dict(document)
    operations = [result.ok() for result in schema.get_all_operations()]
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(
            max_examples=max_examples,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def fuzz(case: schemathesis.Case) -> None:
            case.call_and_validate(
                base_url=url,
                timeout=timeout_s,
                headers=headers,
                excluded_checks=[positive_data_acceptance],
            )

        fuzz()
    return len(operations)


@asynccontextmanager
async def in_process(app: ASGIApp, base_url: str, token: str) -> AsyncIterator[httpx.AsyncClient]:
    """An httpx client on ``app`` in this process, its lifespan run, calling as the controller
    does: with the service token."""
    async with LifespanManager(app) as manager:
        transport = httpx.ASGITransport(app=manager.app)
        async with httpx.AsyncClient(
            transport=transport, base_url=base_url, headers=bearer(token)
        ) as client:
            yield client


async def submitted_search(
    client: httpx.AsyncClient, image: bytes, params: dict[str, str]
) -> dict[str, Any]:
    """Submit the JPEG ``image`` as a search of the demo scene with ``params`` (202 asserted) and
    return the search the controller recorded (its JSON)."""
    answer = await client.post(
        "/searches",
        content=image,
        params={"scene": "demo", **params},
        headers={"content-type": "image/jpeg"},
    )
    assert answer.status_code == 202, answer.text
    recorded: dict[str, Any] = answer.json()
    return recorded
