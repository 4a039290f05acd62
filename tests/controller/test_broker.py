"""The broker: placement heuristics, retries, taking failing replicas out and back, with
injected faults (a scripted transport) and with real slow, failing and hanging replica processes."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from collections.abc import Callable
from urllib.parse import urlsplit

import pytest

from cosmos.launch import running_service
from services.controller.broker import Broker, BrokerError, Heuristic
from services.controller.transport import StageAnswer, StageRequest, TransportError

pytestmark = pytest.mark.anyio


work = StageRequest("POST", "/work")
Behaviour = Callable[[str, StageRequest], StageAnswer]


def answer(status: int, body: object = None) -> StageAnswer:
    return StageAnswer(status, b"" if body is None else json.dumps(body).encode())


class Scripted:
    """A transport whose replicas answer ``behaviour(host, request)`` (or raise)."""

    def __init__(self, behaviour: Behaviour) -> None:
        self.behaviour = behaviour

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        return self.behaviour(urlsplit(base_url).hostname or "", request)

    async def close(self) -> None:
        pass


def mock_broker(behaviour: Behaviour, heuristic=Heuristic.SHORTEST_EXPECTED, **kwargs) -> Broker:
    """Replicas a, b, c served by ``behaviour``."""
    return Broker(
        {"renderer": ["http://a", "http://b", "http://c"]},
        heuristic=heuristic,
        transport=Scripted(behaviour),
        backoff_s=0.0,
        health_interval_s=0,
        **kwargs,
    )


async def test_round_robin_takes_turns():
    broker = mock_broker(lambda host, _: answer(200, {"host": host}), Heuristic.ROUND_ROBIN)
    hosts = [(await broker.call("renderer", "render", work)).json()["host"] for _ in range(6)]
    assert Counter(hosts) == {"a": 2, "b": 2, "c": 2}
    await broker.close()


async def test_least_loaded_avoids_busy_replicas():
    broker = mock_broker(lambda host, _: answer(200), Heuristic.LEAST_LOADED)
    a, b, c = broker.replicas("renderer")
    a.in_flight, b.reported_load, c.in_flight = 3, 5, 1
    assert broker.choose("renderer", "render") is c
    await broker.close()


async def test_shortest_expected_completion_prefers_the_fast_replica():
    broker = mock_broker(lambda host, _: answer(200))
    a, b, c = broker.replicas("renderer")
    a.expected_ms["render"], b.expected_ms["render"], c.expected_ms["render"] = 300.0, 40.0, 90.0
    assert broker.choose("renderer", "render") is b
    b.in_flight = 3  # 4 x 40 ms of work ahead of a new task there: c is quicker now
    assert broker.choose("renderer", "render") is c
    assert broker.choose("renderer", "detect") in (a, b, c)  # no history for that kind yet
    await broker.close()


async def test_a_keyed_task_returns_to_the_replica_that_served_its_key():
    """A search's optimizer tasks go back to the replica that holds its target, while it is no
    busier; when that replica fails the task goes elsewhere, and the key follows it."""
    down: set[str] = set()

    def behaviour(host: str, _: StageRequest) -> StageAnswer:
        return answer(503) if host in down else answer(200, {"host": host})

    broker = mock_broker(behaviour, Heuristic.ROUND_ROBIN)

    async def host_of(kind: str, key: str | None = "s1") -> str:
        return str((await broker.call("renderer", kind, work, key)).json()["host"])

    first = await host_of("target")
    assert [await host_of("refine") for _ in range(4)] == [first] * 4
    unkeyed = [await host_of("refine", None) for _ in range(3)]
    assert Counter(unkeyed) == {"a": 1, "b": 1, "c": 1}  # tasks without a key take turns
    holder = next(r for r in broker.replicas("renderer") if r.url == f"http://{first}")
    holder.in_flight += 1  # busier than the others: the task goes to one of them
    elsewhere = await host_of("refine")
    assert elsewhere != first
    holder.in_flight -= 1
    assert await host_of("refine") == elsewhere  # the key follows the replica that answered
    down.add(elsewhere)
    moved = await host_of("refine")
    assert moved != elsewhere
    down.clear()
    assert await host_of("refine") == moved
    await broker.close()


async def test_connect_errors_and_5xx_go_to_another_replica():
    def behaviour(host, request):
        if host == "a":
            raise TransportError("ClientConnectorError: refused")
        if host == "b":
            return answer(503)
        return answer(200, {"host": host})

    broker = mock_broker(behaviour, Heuristic.ROUND_ROBIN)
    for _ in range(5):
        assert (await broker.call("renderer", "render", work)).json() == {"host": "c"}
    a, b, c = broker.replicas("renderer")
    assert a.failed > 0
    assert b.failed > 0
    assert c.failed == 0
    await broker.close()


async def test_client_errors_are_returned_not_retried():
    calls = Counter()

    def behaviour(host, request):
        calls[host] += 1
        return answer(422, {"detail": "bad"})

    broker = mock_broker(behaviour)
    response = await broker.call("renderer", "render", work)
    assert response.status_code == 422
    assert sum(calls.values()) == 1
    await broker.close()


async def test_a_task_fails_with_reasons_only_when_no_replica_can_serve():
    def behaviour(host, request):
        raise TransportError("timed out (SocketTimeoutError, 60 s)")

    broker = mock_broker(behaviour, max_attempts=4)
    with pytest.raises(BrokerError) as caught:
        await broker.call("renderer", "render", work)
    assert len(caught.value.reasons) == 4
    assert all("timed out" in reason for reason in caught.value.reasons)
    assert "no renderer replica could render" in str(caught.value)
    await broker.close()


async def test_a_failing_replica_is_taken_out_and_probed_back():
    healthy = {"a": False}

    def behaviour(host, request):
        if request.path == "/health":
            return answer(200, {"in_flight": 2}) if healthy[host] else answer(500)
        return answer(500)

    broker = Broker(
        {"renderer": ["http://a"]},
        transport=Scripted(behaviour),
        backoff_s=0.0,
        failure_threshold=2,
        cooldown_s=60.0,
        health_interval_s=0,
    )
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    (a,) = broker.replicas("renderer")
    assert not broker.stats()[0].up
    await broker.probe()
    assert not broker.stats()[0].up  # still failing its health check
    healthy["a"] = True
    await broker.probe()
    assert broker.stats()[0].up
    assert a.reported_load == 2.0
    await broker.close()


async def test_unknown_stage_is_an_error():
    broker = mock_broker(lambda host, _: answer(200))
    with pytest.raises(BrokerError):
        await broker.call("detector", "detect", work)
    await broker.close()


@pytest.mark.slow
async def test_real_replicas_slow_failing_hanging_and_killed(tmp_path):
    """Four real processes: a fast one, a slow one, one answering 500, one that hangs."""
    with (
        running_service(
            "tests.controller.fake_replica:app",
            tmp_path,
            {"FAKE_NAME": "fast", "FAKE_DELAY_MS": "10"},
        ) as fast,
        running_service(
            "tests.controller.fake_replica:app",
            tmp_path,
            {"FAKE_NAME": "slow", "FAKE_DELAY_MS": "150"},
        ) as slow,
        running_service(
            "tests.controller.fake_replica:app",
            tmp_path,
            {"FAKE_NAME": "broken", "FAKE_FAIL": "500"},
        ) as broken,
        running_service(
            "tests.controller.fake_replica:app",
            tmp_path,
            {"FAKE_NAME": "stuck", "FAKE_FAIL": "hang"},
        ) as stuck,
    ):
        broker = Broker(
            {"renderer": [fast.url, slow.url, broken.url, stuck.url]},
            timeouts_s={"renderer": 0.5},
            backoff_s=0.01,
            failure_threshold=1,
            cooldown_s=30.0,
            health_interval_s=0,
        )
        served = Counter()
        for _ in range(3):  # sequential: each replica gets tried, the bad ones drop out
            served[(await broker.call("renderer", "work", work)).json()["replica"]] += 1
        results = await asyncio.gather(*(broker.call("renderer", "work", work) for _ in range(24)))
        served.update(r.json()["replica"] for r in results)
        assert set(served) <= {"fast", "slow"}
        assert served["fast"] > served["slow"]
        names = {r.url: r.name for r in broker.replicas()}
        up = {s.name: s.up for s in broker.stats()}
        assert not up[names[broken.url]]
        assert not up[names[stuck.url]]

        slow.process.terminate()  # a replica dies mid-run: the rest carries on
        slow.process.wait(timeout=10)
        results = await asyncio.gather(*(broker.call("renderer", "work", work) for _ in range(10)))
        assert {r.json()["replica"] for r in results} == {"fast"}
        await broker.close()


async def test_dns_discovery_gives_one_replica_per_address():
    from services.controller.discovery import expand_urls

    urls = await expand_urls(
        ["http://localhost:8001", "http://no-such-host.invalid:1", "http://127.0.0.1:9"]
    )
    assert "http://127.0.0.1:8001" in urls
    assert "http://no-such-host.invalid:1" in urls  # kept as given when it does not resolve
    assert urls.count("http://127.0.0.1:9") == 1


async def test_a_new_pool_keeps_what_is_known_of_remaining_replicas():
    broker = mock_broker(lambda host, _: answer(200))
    a = broker.replicas("renderer")[0]
    a.expected_ms["render"] = 42.0
    await broker.set_pool("renderer", ["http://a", "http://d"])
    assert [r.url for r in broker.replicas("renderer")] == ["http://a", "http://d"]
    assert broker.replicas("renderer")[0].expected_ms == {"render": 42.0}
    await broker.close()


async def test_replicas_are_shown_by_name_and_state_never_by_address():
    """``renderer-1``.. in the order the broker met them; a replica keeps its name when the pool
    changes and a new address gets a new number, so a name never means two replicas."""
    failing = {"b"}

    def behaviour(host, _):
        if host in failing:
            raise TransportError("refused")
        return answer(200)

    broker = mock_broker(behaviour, heuristic=Heuristic.ROUND_ROBIN, failure_threshold=2)
    for _ in range(3):
        await broker.call("renderer", "render", work)
    stats = {s.name: s for s in broker.stats()}
    assert list(stats) == ["renderer-1", "renderer-2", "renderer-3"]
    assert stats["renderer-1"].state == "up"
    assert stats["renderer-2"].state == "failing"  # failed once, still gets tasks
    assert stats["renderer-1"].expected_ms["render"] >= 0
    for _ in range(6):
        await broker.call("renderer", "render", work)
    assert {s.name: s.state for s in broker.stats()}["renderer-2"] == "out"
    await broker.set_pool("renderer", ["http://c", "http://d", "http://a"])
    assert [(s.name, s.stage) for s in broker.stats()] == [
        ("renderer-3", "renderer"),
        ("renderer-4", "renderer"),
        ("renderer-1", "renderer"),
    ]
    shown = json.dumps([s.model_dump(mode="json") for s in broker.stats()])
    assert "http" not in shown
    await broker.close()


async def test_outages_say_why_a_stage_is_unavailable():
    up = {"a": False, "b": False, "c": False}
    broker = outage_broker(up)
    await broker.set_pool("detector", [])
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    assert broker.outages() == {
        "renderer": "no replica could serve its last task, and none has answered since",
        "detector": "it has no replica",
    }
    for replica in broker.replicas("renderer"):
        replica.down_until = float("inf")
    assert "every replica failed" in broker.outages()["renderer"]
    assert broker.unavailable() == ["renderer", "detector"]
    await broker.close()


# -- outages: a stage no replica serves ---------------------------------------------------------


def outage_broker(up: dict[str, bool], health_calls: Counter | None = None) -> Broker:
    """Replicas a, b, c: tasks and ``/health`` fail while ``up[host]`` is false."""

    def behaviour(host, request):
        if request.path == "/health" and health_calls is not None:
            health_calls[host] += 1
        if not up[host]:
            raise TransportError("ClientConnectorError: refused")
        return answer(200, {"in_flight": 0})

    return mock_broker(behaviour, recovery_probe_s=0.01)


async def test_a_stage_is_unavailable_from_a_task_nobody_served_until_a_replica_answers():
    up = {"a": False, "b": False, "c": False}
    broker = outage_broker(up)
    assert broker.unavailable() == []
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    # not every replica is out yet (3 of 4 attempts spread over 3), but nobody served the task
    assert any(r.up for r in broker.stats())
    assert broker.unavailable() == ["renderer"]
    await broker.probe()
    assert broker.unavailable() == ["renderer"]
    up["b"] = True
    await broker.probe()
    assert broker.unavailable() == []
    await broker.close()


async def test_a_stage_whose_every_replica_is_out_or_that_has_none_is_unavailable():
    broker = outage_broker({"a": True, "b": True, "c": True})
    for replica in broker.replicas("renderer"):
        replica.down_until = float("inf")
    await broker.set_pool("detector", [])
    assert broker.unavailable() == ["renderer", "detector"]
    await broker.close()


async def test_waiting_for_a_replica_probes_the_stage_until_one_answers():
    up = {"a": False, "b": False, "c": False}
    health = Counter()
    broker = outage_broker(up, health)
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    waiters = [asyncio.create_task(broker.wait_for_replica("renderer", 10.0)) for _ in range(20)]
    await asyncio.sleep(0.1)
    assert not any(w.done() for w in waiters)
    probed = sum(health.values())
    assert 3 * 3 <= probed <= 3 * 12  # one prober for every waiter: ~10 rounds of 3 probes
    up["c"] = True
    assert await asyncio.wait_for(asyncio.gather(*waiters), 1.0) == [True] * 20
    assert broker.unavailable() == []
    assert (await broker.call("renderer", "render", work)).status_code == 200
    await asyncio.sleep(0.05)
    assert all(task.done() for task in broker._recoveries.values())  # nobody waits: no probes
    await broker.close()


async def test_a_wait_for_a_stage_that_stays_away_times_out():
    health = Counter()
    broker = outage_broker({"a": False, "b": False, "c": False}, health)
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    assert not await broker.wait_for_replica("renderer", 0.05)
    await asyncio.sleep(0.05)
    probed = sum(health.values())
    await asyncio.sleep(0.05)
    assert sum(health.values()) == probed  # the prober stopped with its last waiter
    assert broker.unavailable() == ["renderer"]
    await broker.close()


async def test_a_wait_for_a_stage_that_answered_meanwhile_returns_at_once():
    up = {"a": False, "b": False, "c": False}
    broker = outage_broker(up)
    with pytest.raises(BrokerError):
        await broker.call("renderer", "render", work)
    up.update(a=True, b=True, c=True)
    await broker.probe()
    assert await asyncio.wait_for(broker.wait_for_replica("renderer", 10.0), 0.01)
    await broker.close()


class LateLoop:
    """A transport whose calls time out as seen by a loop that was blocked ``late_s`` past the
    timeout, ``times`` times, then answer 200."""

    def __init__(self, late_s: float, times: int) -> None:
        self.late_s, self.times, self.calls = late_s, times, 0

    async def send(self, base_url: str, request: StageRequest, timeout_s: float) -> StageAnswer:
        self.calls += 1
        if self.calls <= self.times:
            raise TransportError("timed out (ConnectionTimeoutError, 2 s)", late_s=self.late_s)
        return answer(200, {"ok": True})

    async def close(self) -> None:
        pass


async def test_timeouts_noticed_late_by_this_loop_do_not_take_the_replica_out():
    broker = Broker(
        {"renderer": ["http://a"]},
        transport=LateLoop(late_s=3.0, times=6),
        backoff_s=0.0,
        failure_threshold=1,
        health_interval_s=0,
    )
    with pytest.raises(BrokerError) as caught:  # four attempts, each a stall of this loop
        await broker.call("renderer", "render", work)
    assert "noticed 3.0 s late" in caught.value.reasons[0]
    assert broker.stats()[0].up  # not counted against it, though one failure would take it out
    assert broker.stats()[0].failed == 0
    assert broker.unavailable() == []  # and the stage is not reported unavailable
    await broker.probe()  # a probe that stalls too gives no verdict either
    assert broker.stats()[0].up
    assert (await broker.call("renderer", "render", work)).status_code == 200
    await broker.close()


async def test_timeouts_on_time_still_count_against_the_replica():
    broker = Broker(
        {"renderer": ["http://a"]},
        transport=LateLoop(late_s=0.01, times=1),
        backoff_s=0.0,
        failure_threshold=1,
        cooldown_s=60.0,
        health_interval_s=0,
    )
    assert (await broker.call("renderer", "render", work)).status_code == 200  # on the retry
    assert broker.stats()[0].failed == 1
    await broker.close()
