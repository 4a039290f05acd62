"""The fault suite of issue 15 through the real processes of one local stack (2 renderers,
1 detector, the optimizer and the controller, on loopback): each scenario of
:mod:`cosmos.bench.faults.scenarios` with short loads and faults (``Timing.quick``: the
detector away 5 s, with an outage budget of 20 s), asserting that no normal search is lost,
that those that should succeed do, and each scenario's own facts. ``python -m
benchmarks.faults`` runs the same scenarios at full length and prints their figures.

The scenarios share the stack and run in file order, the uploads last.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from cosmos.bench.faults.clients import maximal_uploads, slow_clients, tenants
from cosmos.bench.faults.results import ScenarioResult
from cosmos.bench.faults.rig import Rig, fault_rig
from cosmos.bench.faults.scenarios import (
    controller_killed,
    detector_outage,
    replica_killed,
    replica_killed_supervised,
)
from cosmos.bench.faults.under_load import Timing

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

TIMING = Timing.quick()
OUTAGE_BUDGET_S = 20.0  # longer than the 5 s outage, far shorter than the default 60 s


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    env = {"COSMOS_CONTROLLER_OUTAGE_BUDGET_S": str(OUTAGE_BUDGET_S)}
    with fault_rig(tmp_path_factory.mktemp("faults"), env=env) as running:
        yield running


def assert_none_lost(result: ScenarioResult, at_least: int = 1) -> None:
    """Every normal search the controller took succeeded, and there were some."""
    counts = result.measured.counts
    assert counts.lost == 0, (result.notes(), result.measured.errors)
    assert counts.unfinished == counts.failed == 0
    assert counts.submitted >= at_least, result.notes()
    assert counts.succeeded == counts.submitted
    assert set(result.measured.peak_rss_mib) == {"renderer", "detector", "optimizer", "controller"}
    assert all(mib > 10 for mib in result.measured.peak_rss_mib.values())


def test_two_tenants_cannot_see_each_others_searches(rig):
    result = tenants(rig, TIMING)
    assert_none_lost(result)
    assert result.a_searches >= 1
    assert result.b_searches >= 1
    assert result.checks >= 3 * result.a_searches + result.b_searches
    assert result.b_saw_a == 0  # 404 for every read and cancel, and none in B's list
    assert result.a_saw_b == 0
    assert result.b_lists_own


def test_a_replica_killed_under_supervision_comes_back(rig):
    result = replica_killed_supervised(rig, TIMING)
    assert_none_lost(result)
    assert result.supervised
    assert result.came_back, result.notes()
    assert result.restarts == 1
    assert any("exited (signal 9)" in line for line in rig.said), rig.said
    assert not rig.supervised  # supervision ended with the scenario


def test_a_replica_killed_without_supervision_is_taken_back_when_started_again(rig):
    result = replica_killed(rig, TIMING)
    assert_none_lost(result)
    assert not result.supervised
    assert result.came_back, result.notes()
    assert result.back_after_s >= TIMING.degraded_s  # the stage ran on its other replica


def test_searches_ride_out_the_only_detectors_outage(rig):
    result = detector_outage(rig, TIMING)
    assert_none_lost(result)
    assert result.outage_s >= TIMING.outage_s
    assert result.degraded_seen
    assert result.in_flight >= 1
    assert result.ridden_out >= 1  # the sentinel, 2 of its 12 iterations done, had to wait
    assert result.measured.counts.refused == 0  # asked again until taken


def test_a_killed_controller_is_restarted_and_resumes_its_searches(rig):
    result = controller_killed(rig, TIMING)
    assert_none_lost(result)
    assert result.in_flight >= 1
    assert result.resumed >= 1  # the sentinel, at least, finished on the new controller
    assert result.orphans_unfinished == 0


def test_health_answers_while_slow_clients_hold_hundreds_of_sockets(rig):
    result = slow_clients(rig, TIMING)
    assert_none_lost(result)
    assert result.sockets == TIMING.slow_sockets
    assert result.health_checks >= 10
    assert result.health_failures == 0
    assert result.closed_by_server == result.sockets  # held past the 10 s head deadline


def test_every_maximal_upload_is_answered_and_normal_searches_go_on(rig):
    result = maximal_uploads(rig, TIMING)
    assert_none_lost(result)
    assert result.limit_bytes - 64 * 1024 < result.body_bytes <= result.limit_bytes
    assert result.unanswered == 0, result.facts()
    assert result.badly_answered == 0, result.statuses
    assert sum(result.statuses.values()) == result.uploads == 50
    assert result.statuses.get(202, 0) >= 1, result.statuses
    assert all(status < 500 or status == 503 for status in result.statuses)
    # Held whole, the 50 bodies alone would take 1000 MiB (2.7 GiB peak before the body budget);
    # bounded, the controller holds a few at a time.
    all_bodies_mib = result.uploads * result.body_bytes / 2**20
    assert result.measured.peak_rss_mib["controller"] < 0.75 * all_bodies_mib, result.measured
