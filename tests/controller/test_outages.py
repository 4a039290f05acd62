"""Outages, with the real renderer, detector and optimizer apps in process behind a transport that
can take one down: running searches wait for a stage that comes back within the outage budget and
succeed; a search that waited longer fails saying so, and once the stage is back, resumes with
``POST /searches/{id}/retry``; meanwhile ``/health`` says ``degraded`` and new submissions are
refused with 503 and ``Retry-After``. No answer names a replica's address."""

from __future__ import annotations

import asyncio
import os
import re
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
from asgi_lifespan import LifespanManager
from fastapi import FastAPI
from starlette.types import ASGIApp

from services.common.auth import TOKEN_VARIABLE, bearer
from services.controller.app import create_app as create_controller
from services.controller.settings import ControllerSettings
from services.controller.transport import StageAnswer, StageRequest, TransportError
from services.detector.app import create_app as create_detector
from services.optimizer.app import create_app as create_optimizer
from services.renderer.app import create_app as create_renderer
from tests.controller.clients import key_client, new_key

pytestmark = pytest.mark.anyio

ADDRESS = re.compile(r"https?://|\b\d{1,3}(\.\d{1,3}){3}\b|localhost|:\d{2,5}\b")
OUTAGE = "urn:cosmos:problem:stage-unavailable"


@pytest.fixture(scope="module")
async def apps() -> AsyncIterator[dict[str, ASGIApp]]:
    async with (
        LifespanManager(create_renderer()) as renderer,
        LifespanManager(create_detector()) as detector,
        LifespanManager(create_optimizer()) as optimizer,
    ):
        yield {"renderer": renderer.app, "detector": detector.app, "optimizer": optimizer.app}


class Switchable:
    """A transport to the in-process app named by the URL's host (``renderer`` and so on).

    A host in ``down`` refuses connections, ``/health`` too, as a stopped process would; with
    ``stop_after[host] = n`` it goes down by itself once it has served ``n`` tasks.
    """

    def __init__(self, apps: dict[str, ASGIApp]) -> None:
        self.clients = {
            host: httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://app")
            for host, app in apps.items()
        }
        self.down: set[str] = set()
        self.stop_after: dict[str, int] = {}
        self.served: Counter[str] = Counter()

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        host = urlsplit(base_url).hostname or ""
        if request.path != "/health" and self.served[host] >= self.stop_after.get(host, 1 << 30):
            self.down.add(host)
        if host in self.down:
            raise TransportError(f"ClientConnectorError: Cannot connect to host {host}:8002")
        if request.path != "/health":
            self.served[host] += 1
        response = await self.clients[host].request(
            request.method, request.path, content=request.body, headers=dict(request.headers)
        )
        return StageAnswer(response.status_code, response.content, dict(response.headers))

    def start(self, host: str) -> None:
        """Bring ``host`` back (to stay)."""
        self.down.discard(host)
        self.stop_after.pop(host, None)

    async def close(self) -> None:
        pass  # the clients outlive one controller: the module's apps serve several tests


@asynccontextmanager
async def controller(
    tmp_path: Path, transport: Switchable, outage_budget_s: float
) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """A controller over ``transport``, and a client with a tenant's key."""
    settings = ControllerSettings(
        controller_renderer_urls="http://renderer",
        controller_detector_urls="http://detector",
        controller_optimizer_urls="http://optimizer",
        controller_database_url=f"sqlite:///{tmp_path / 'controller.sqlite3'}",
        controller_outage_budget_s=outage_budget_s,
    )
    app = create_controller(settings, transport=transport)
    async with LifespanManager(app) as running:
        async with key_client(running.app, new_key(app, "tenant")) as client:
            yield app, client


async def target_png(apps: dict[str, ASGIApp], lat: int, lon: int) -> bytes:
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=apps["renderer"]),
        base_url="http://renderer",
        headers=bearer(os.environ[TOKEN_VARIABLE]),  # the session's (tests/conftest.py)
    ) as renderer:
        response = await renderer.post(
            "/render", json={"scene": "demo", "pose": {"lat": lat, "lon": lon}}
        )
    assert response.status_code == 200, response.text
    return response.content


async def submit(client: httpx.AsyncClient, image: bytes) -> httpx.Response:
    return await client.post(
        "/searches",
        content=image,
        params={"scene": "demo", "start_theta_deg": "60", "start_phi_deg": "180"},
        headers={"Content-Type": "image/png"},
    )


async def until(check: Callable[[], Any], timeout_s: float = 60.0) -> Any:
    """The first true result of the awaitable ``check()``, polled."""
    deadline = time.monotonic() + timeout_s
    while not (result := await check()):
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.05)
    return result


async def finished(client: httpx.AsyncClient, search_id: str) -> dict[str, Any]:
    async def check() -> dict[str, Any] | None:
        search = (await client.get(f"/searches/{search_id}")).json()
        return search if search["status"] not in {"queued", "running"} else None

    found: dict[str, Any] = await until(check)
    return found


async def health(client: httpx.AsyncClient) -> dict[str, Any]:
    response = await client.get("/health")
    assert response.status_code == 200
    body: dict[str, Any] = response.json()
    return body


def assert_refused_while_down(response: httpx.Response, stage: str) -> None:
    assert response.status_code == 503, response.text
    assert response.headers["retry-after"] == "5"
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert problem["type"] == OUTAGE
    assert f"the {stage} is unavailable" in problem["detail"]
    assert not ADDRESS.search(problem["detail"]), problem["detail"]
    assert "http://" not in response.text


async def test_running_searches_ride_out_a_short_detector_outage(apps, tmp_path):
    transport = Switchable(apps)
    image = await target_png(apps, 3, 7)
    async with controller(tmp_path, transport, outage_budget_s=60.0) as (_, client):
        assert (await health(client))["status"] == "ok"
        transport.stop_after["detector"] = 3  # both targets and one view: then it stops
        submitted = [await submit(client, image) for _ in range(2)]
        assert [r.status_code for r in submitted] == [202, 202]
        ids = [r.json()["id"] for r in submitted]

        async def degraded() -> bool:
            return (await health(client))["status"] == "degraded"

        await until(degraded)
        assert (await health(client))["unavailable_stages"] == ["detector"]
        assert_refused_while_down(await submit(client, image), "detector")
        for search_id in ids:
            assert (await client.get(f"/searches/{search_id}")).json()["status"] == "running"

        await asyncio.sleep(1.0)  # the outage lasts a while; the searches wait
        transport.start("detector")
        for search_id in ids:
            search = await finished(client, search_id)
            assert search["status"] == "succeeded", search["error"]
            assert search["result"]["pose"]["index"] == {"lat": 3, "lon": 7}
        assert (await health(client))["status"] == "ok"
        assert (await submit(client, image)).status_code == 202


async def test_a_search_an_outage_outlasted_fails_saying_so_and_resumes_when_retried(
    apps, tmp_path
):
    transport = Switchable(apps)
    image = await target_png(apps, 3, 7)
    async with controller(tmp_path, transport, outage_budget_s=1.0) as (app, client):
        transport.stop_after["detector"] = 2  # the target and the start view
        submitted = await submit(client, image)
        assert submitted.status_code == 202, submitted.text
        search_id = submitted.json()["id"]
        failed = await finished(client, search_id)
        assert failed["status"] == "failed"
        error = failed["error"]
        assert error["type"] == OUTAGE
        assert error["title"] == "No detector available"
        assert "the detector was unavailable" in error["detail"]
        assert "did not come back within 1 s" in error["detail"]
        assert f"POST /searches/{search_id}/retry" in error["detail"]
        assert not ADDRESS.search(error["detail"]), error["detail"]
        assert len(failed["iterations"]) == 1  # the start view's, recorded before the failure

        assert_refused_while_down(await client.post(f"/searches/{search_id}/retry"), "detector")
        async with key_client(app, new_key(app, "other")) as other:  # another tenant's search
            assert (await other.post(f"/searches/{search_id}/retry")).status_code == 404
        transport.start("detector")

        async def back() -> bool:
            return (await health(client))["status"] == "ok"

        await until(back, timeout_s=10.0)  # the broker's health probe sees it
        retried = await client.post(f"/searches/{search_id}/retry")
        assert retried.status_code == 202, retried.text
        assert retried.headers["location"] == f"/searches/{search_id}"
        assert retried.json()["status"] == "queued"
        assert retried.json()["error"] is None
        final = await finished(client, search_id)
        assert final["status"] == "succeeded", final["error"]
        assert final["iterations"][0] == failed["iterations"][0]  # resumed, not started over
        assert [it["index"] for it in final["iterations"]] == list(range(len(final["iterations"])))
        assert final["result"]["pose"]["index"] == {"lat": 3, "lon": 7}

        again = await client.post(f"/searches/{search_id}/retry")
        assert again.status_code == 409
        assert again.headers["content-type"] == "application/problem+json"
        assert again.json()["type"] == "urn:cosmos:problem:not-retryable"
        assert (await client.post("/searches/nope/retry")).status_code == 404


async def test_stage_errors_of_the_api_name_the_stage_not_its_replicas(apps, tmp_path):
    transport = Switchable(apps)
    transport.down.add("renderer")
    async with controller(tmp_path, transport, outage_budget_s=60.0) as (_, client):
        assert_refused_while_down(await client.get("/scenes"), "renderer")
        assert (await health(client))["unavailable_stages"] == ["renderer"]
        refused = await submit(client, await target_png(apps, 3, 7))
        assert_refused_while_down(refused, "renderer")
