"""The controller's readiness: its database answers and every stage has a replica that says it
is ready, asked afresh."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest

from services.controller.broker import Broker
from services.controller.readiness import ControllerReadiness
from services.controller.store import SearchStore
from services.controller.transport import StageAnswer, StageRequest, TransportError

pytestmark = pytest.mark.anyio


class Replicas:
    """Replicas by host name: ``ready``, ``busy`` (503) or ``down`` (no answer); records what
    each was sent."""

    def __init__(self, states: dict[str, str]) -> None:
        self.states = states
        self.sent: list[tuple[str, StageRequest]] = []

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        host = urlsplit(base_url).hostname or ""
        self.sent.append((host, request))
        state = self.states[host]
        if state == "down":
            raise TransportError("connection refused")
        return StageAnswer(200 if state == "ready" else 503, b"{}")

    async def close(self) -> None:
        pass


def readiness(states: dict[str, str], store: SearchStore) -> tuple[ControllerReadiness, Replicas]:
    replicas = Replicas(states)
    pools = {
        "renderer": ["http://r1", "http://r2"],
        "detector": ["http://d1"],
        "optimizer": ["http://o1"],
    }
    broker = Broker(pools, transport=replicas, health_interval_s=0)
    return ControllerReadiness(store, broker, replicas), replicas


@pytest.fixture
def store():
    store = SearchStore("sqlite:///:memory:")
    yield store
    store.close()


async def test_one_ready_replica_per_stage_is_enough(store):
    check, replicas = readiness({"r1": "down", "r2": "ready", "d1": "ready", "o1": "ready"}, store)
    assert await check.unready() == []
    assert {(host, r.method, r.path) for host, r in replicas.sent} == {
        (host, "GET", "/readyz") for host in ("r1", "r2", "d1", "o1")
    }


async def test_a_stage_without_a_ready_replica_is_named(store):
    check, _ = readiness({"r1": "down", "r2": "busy", "d1": "ready", "o1": "down"}, store)
    assert await check.unready() == [
        "no renderer is ready (2 replicas asked)",
        "no optimizer is ready (1 replica asked)",
    ]


async def test_a_closed_database_is_named():
    store = SearchStore("sqlite:///:memory:")
    check, _ = readiness({"r1": "ready", "r2": "ready", "d1": "ready", "o1": "ready"}, store)
    store.close()
    assert await check.unready() == ["the search database does not answer"]


async def test_the_controllers_probes(controller, service_token):
    """The fixture's controller has a renderer (in process, with the token) and no detector or
    optimizer: alive, not ready, and it says why."""
    app, client = controller
    assert (await client.get("/livez")).json() == {"status": "ok", "service": "controller"}
    response = await client.get("/readyz")
    assert response.status_code == 503
    assert response.json()["reasons"] == [
        "no detector is ready (1 replica asked)",
        "no optimizer is ready (1 replica asked)",
    ]
    scenes = await client.get("/scenes")  # through the broker, with the token
    assert scenes.status_code == 200, scenes.text
