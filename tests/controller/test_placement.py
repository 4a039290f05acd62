"""The broker's replica choice and what it learns (services.controller.placement), as pure code:
the live broker and benchmarks.broker_sim both run it."""

from __future__ import annotations

import pytest

from services.controller.broker import Broker
from services.controller.placement import (
    DEFAULT_EXPECTED_MS,
    EWMA_WEIGHT,
    Heuristic,
    Replica,
    candidates,
    choose,
    expected_ms,
)


def pool(*loads: float, **expected: float) -> list[Replica]:
    """Replicas a, b, c, … with these tasks in flight and render averages (by name)."""
    replicas = []
    for i, load in enumerate(loads):
        name = "abcdefgh"[i]
        replica = Replica(stage="renderer", url=f"http://{name}", name=name, in_flight=int(load))
        if name in expected:
            replica.expected_ms["render"] = expected[name]
        replicas.append(replica)
    return replicas


def test_round_robin_follows_the_turn():
    replicas = pool(5, 0, 0)
    picks = [
        choose(Heuristic.ROUND_ROBIN, replicas, "render", turn=t, now=0).name for t in range(4)
    ]
    assert picks == ["a", "b", "c", "a"]


def test_least_loaded_takes_the_fewest_in_flight_and_ties_take_turns():
    replicas = pool(2, 1, 1)
    picks = {
        choose(Heuristic.LEAST_LOADED, replicas, "render", turn=t, now=0).name for t in range(3)
    }
    assert picks == {"b", "c"}


def test_reported_load_counts_what_is_beyond_this_controllers_own():
    replicas = pool(0, 1)
    replicas[0].reported_load = 3.0  # another controller's tasks
    assert replicas[0].load == 3.0
    assert choose(Heuristic.LEAST_LOADED, replicas, "render", turn=0, now=0).name == "b"


def test_a_report_of_this_controllers_own_tasks_goes_stale_with_them():
    replica = pool(4)[0]
    replica.answered_health(5.0)  # its 4 and one from another controller
    assert replica.load == 5.0
    replica.in_flight = 0  # this controller's 4 answered since
    assert replica.load == 1.0  # not 5 until the next probe
    replica.in_flight = 2
    assert replica.load == 3.0


def test_shortest_expected_weighs_load_by_duration():
    # a: (2 + 1) · 100 = 300; b: (0 + 1) · 400 = 400; c: (1 + 1) · 120 = 240
    replicas = pool(2, 0, 1, a=100.0, b=400.0, c=120.0)
    assert choose(Heuristic.SHORTEST_EXPECTED, replicas, "render", turn=0, now=0).name == "c"


def test_a_replica_without_history_is_as_fast_as_the_pool_mean():
    replicas = pool(0, 0, 0, a=100.0, b=300.0)
    assert expected_ms(replicas[2], "render", replicas) == pytest.approx(200.0)
    assert expected_ms(replicas[0], "detect", replicas) == DEFAULT_EXPECTED_MS
    replicas[0].in_flight = 2  # a: (2 + 1) · 100 = 300, b: 300, c: (0 + 1) · 200 (assumed)
    assert choose(Heuristic.SHORTEST_EXPECTED, replicas, "render", turn=0, now=0).name == "c"


def test_out_and_excluded_replicas_are_skipped_unless_nothing_else_is_left():
    replicas = pool(0, 5, 5)
    replicas[0].down_until = 10.0
    assert [r.name for r in candidates(replicas, 5.0, {"http://b"})] == ["c"]
    assert choose(Heuristic.LEAST_LOADED, replicas, "render", turn=0, now=5.0).name == "b"
    assert choose(Heuristic.LEAST_LOADED, replicas, "render", turn=0, now=10.0).name == "a"
    everyone = {"http://a", "http://b", "http://c"}
    assert [r.name for r in candidates(replicas, 5.0, {"http://b", "http://c"})] == ["a"]
    assert [r.name for r in candidates(replicas, 5.0, everyone)] == ["a", "b", "c"]
    with pytest.raises(ValueError, match="empty pool"):
        choose(Heuristic.LEAST_LOADED, [], "render", turn=0, now=0)


@pytest.mark.parametrize("heuristic", list(Heuristic))
def test_a_preferred_replica_takes_the_task_unless_it_is_busier(heuristic):
    """The replica that holds the task's data takes it while it has no more tasks ahead than
    the heuristic's choice; busier, out or excluded, it does not."""
    replicas = pool(0, 0, 0, a=50.0, b=50.0, c=50.0)
    for turn in range(3):
        held = choose(heuristic, replicas, "render", turn=turn, now=0, prefer="http://c")
        assert held.name == "c"
    replicas[2].in_flight = 1
    picks = {
        choose(heuristic, replicas, "render", turn=t, now=0, prefer="http://c").name
        for t in range(3)
    }
    # round-robin still gives c its own turn; the others keep the task from the busier c
    assert picks == ({"a", "b", "c"} if heuristic is Heuristic.ROUND_ROBIN else {"a", "b"})
    replicas[2].in_flight = 0
    excluded = choose(
        heuristic, replicas, "render", turn=0, now=0, exclude={"http://c"}, prefer="http://c"
    )
    assert excluded.name != "c"
    replicas[2].down_until = 10.0
    assert choose(heuristic, replicas, "render", turn=0, now=0, prefer="http://c").name != "c"
    assert choose(heuristic, replicas, "render", turn=0, now=0, prefer="http://z").name == "a"


def test_success_failure_and_health_update_what_is_known():
    replica = pool(0)[0]
    replica.succeeded("render", 100.0)
    replica.succeeded("render", 200.0)
    assert replica.expected_ms["render"] == pytest.approx(100.0 + EWMA_WEIGHT * 100.0)
    assert replica.failed_at(1.0, threshold=2, cooldown_s=5.0) is False
    assert replica.state(1.0) == "failing"
    assert replica.failed_at(2.0, threshold=2, cooldown_s=5.0) is True
    assert replica.state(6.9) == "out"
    assert replica.available(7.0)
    replica.failed_at(8.0, threshold=2, cooldown_s=5.0)
    replica.answered_health(4.0)
    assert (replica.state(8.0), replica.load) == ("up", 4.0)
    assert (replica.served, replica.failed) == (2, 3)


def test_the_live_broker_chooses_with_the_same_function():
    broker = Broker({"renderer": ["http://a", "http://b", "http://c"]}, health_interval_s=0)
    live = broker.replicas("renderer")
    for replica, (load, ms) in zip(live, [(1, 100.0), (0, 250.0), (2, 60.0)], strict=True):
        replica.in_flight, replica.expected_ms["render"] = load, ms
    for turn in range(3):
        expected = choose(broker.heuristic, live, "render", turn=turn, now=0.0)
        assert broker.choose("renderer", "render") is expected
    assert expected.name == "renderer-3"  # (2 + 1) · 60 = 180 < 200 < 250
