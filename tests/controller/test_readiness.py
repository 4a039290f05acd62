"""The controller's readiness: its database answers and every stage has a replica that says it
is ready, asked afresh."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest

from services.controller.broker import Broker, BrokerError
from services.controller.readiness import ControllerReadiness
from services.controller.store import SearchStore, open_store
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
    store = open_store("sqlite:///:memory:")
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
    store = open_store("sqlite:///:memory:")
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


async def test_a_stage_in_an_outage_is_not_ready_whatever_its_probe_says(store):
    """What refuses new searches (the broker's outage state) makes the controller unready too:
    a stage whose last task no replica served, until a replica answers the broker again, and a
    stage left without replicas."""
    states = {"r1": "down", "r2": "down", "d1": "ready", "o1": "ready"}
    check, _ = readiness(states, store)
    with pytest.raises(BrokerError):
        await check.broker.call("renderer", "render", StageRequest("POST", "/render"))
    states.update(r1="ready", r2="ready")  # back, but the broker has not heard yet
    assert await check.unready() == [
        "the renderer is unavailable: no replica could serve its last task, and none has "
        "answered since"
    ]
    await check.broker.probe()
    assert await check.unready() == []
    await check.broker.set_pool("optimizer", [])  # discovery found none
    assert await check.unready() == ["the optimizer is unavailable: it has no replica"]


async def test_the_controllers_health_and_readiness_name_replicas_not_addresses(controller):
    """The fixture's detector and optimizer answer 503: once a task found no detector, /readyz
    says so in its problem details and /health is degraded, both without an address."""
    app, client = controller
    broker = app.state.controller.broker
    with pytest.raises(BrokerError):
        await broker.call("detector", "detect", StageRequest("POST", "/detect"))
    ready = await client.get("/readyz")
    assert ready.status_code == 503
    assert ready.headers["content-type"] == "application/problem+json"
    assert ready.json()["reasons"] == [
        "the detector is unavailable: every replica failed repeatedly and is out until it "
        "answers again",
        "no optimizer is ready (1 replica asked)",
    ]
    health = await client.get("/health", headers={"Authorization": ""})  # open to anyone
    assert health.status_code == 200
    body = health.json()
    assert body["status"] == "degraded"
    assert body["unavailable_stages"] == ["detector"]
    assert [(r["name"], r["stage"]) for r in body["replicas"]] == [
        ("renderer-1", "renderer"),
        ("detector-1", "detector"),
        ("optimizer-1", "optimizer"),
    ]
    assert [(r["state"], r["up"]) for r in body["replicas"][:2]] == [("up", True), ("out", False)]
    for text in (health.text, ready.text):
        assert "://" not in text
