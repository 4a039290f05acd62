"""The fault scenarios of issue 15, each through the real processes of a :class:`~.rig.Rig`.

Every scenario runs a background load of normal searches (:class:`~.harness.Load`:
``Timing.concurrency`` clients with a tenant API key of the scenario's own) and samples every
process's memory (:class:`~.harness.RssSampler`) while it injects its fault: ``warm_s`` of load
first, then the fault, then ``after_s`` of load once the stack has recovered; then the load
stops and the searches in flight are followed to their end (``drain_s`` at most). The fault's
window runs from its injection to the stack's recovery (the replica back in the broker, the
controller healthy again, the slow sockets closed, every upload answered); the p95 latency is
that of the normal searches whose life overlaps it. :mod:`.harness` says what counts as
submitted, succeeded and lost.

Where a fact needs a search in flight across the fault (an outage ridden out, a restarted
controller resuming), a sentinel client runs longer searches beside the load (the ``simple``
strategy from near the pole to :data:`~.rig.FAR`: 12 iterations, ~3 s on an idle machine), and
the fault waits until one of them has recorded two iterations; sentinels count among the normal
searches.

Each scenario is a function of a rig and a :class:`~.under_load.Timing` returning its own result
type (:mod:`.results`). This module holds the faults that strike processes (a replica, the only
detector, the controller killed) and :data:`SCENARIOS`, every scenario by name, with
:func:`run_scenarios`, which runs a selection on one rig; :mod:`.clients` holds those that come
from clients (slow clients, maximal uploads, tenants).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Final

from cosmos.bench.faults.clients import maximal_uploads, slow_clients, tenants
from cosmos.bench.faults.results import (
    ControllerKilled,
    DetectorOutage,
    ReplicaKilled,
    ScenarioFailure,
    ScenarioResult,
)
from cosmos.bench.faults.rig import Rig, fault_rig, wait_until
from cosmos.bench.faults.under_load import Timing, UnderLoad, in_flight_at, listed
from services.common.contracts.search import TERMINAL_STATUSES
from services.controller.settings import ControllerSettings

__all__ = [
    "SCENARIOS",
    "Scenario",
    "controller_killed",
    "detector_outage",
    "replica_killed",
    "replica_killed_supervised",
    "run_scenarios",
]


def replica_killed(rig: Rig, timing: Timing) -> ReplicaKilled:
    """SIGKILL the last renderer replica mid-load (its stage keeps another). Supervised
    (:meth:`Rig.supervising`), the supervisor starts it again; plain, it stays dead for
    ``degraded_s`` and is then started again on its port. The window ends when the broker
    counts it up again."""
    renderers = rig.replicas("renderer")
    if len(renderers) < 2:
        raise ValueError("killing a replica mid-load needs a stage with two replicas")
    victim = renderers[-1]
    name = "replica-killed-supervised" if rig.supervised else "replica-killed-plain"
    with UnderLoad(rig, timing, name, seed=1000) as run:
        run.warm()
        started = run.begin()
        restarts = rig.restarts(victim.url)
        plan = rig.kill(victim)
        came_back = True
        try:
            if rig.supervised:
                wait_until(lambda: rig.restarts(victim.url) > restarts, timing.recover_s)
            else:
                time.sleep(timing.degraded_s)
                rig.restart(plan, timing.recover_s)
            wait_until(lambda: rig.replica_up(victim.url), timing.recover_s, interval_s=0.2)
        except TimeoutError:
            came_back = False
        back = run.end()
        served_then = rig.served(victim.url)
        measured = run.finish()
    return ReplicaKilled(
        measured,
        supervised=rig.supervised,
        killed="renderer",
        came_back=came_back,
        back_after_s=back - started,
        restarts=rig.restarts(victim.url) - restarts,
        served_after=rig.served(victim.url) - served_then,
    )


def replica_killed_supervised(rig: Rig, timing: Timing) -> ReplicaKilled:
    """:func:`replica_killed` under ``cosmos up``'s supervision."""
    with rig.supervising():
        return replica_killed(rig, timing)


def _budget_s(rig: Rig) -> float:
    default = ControllerSettings.model_fields["controller_outage_budget_s"].default
    return float(rig.setting("COSMOS_CONTROLLER_OUTAGE_BUDGET_S", str(default)))


def detector_outage(rig: Rig, timing: Timing) -> DetectorOutage:
    """Every detector replica SIGKILLed mid-load, started again ``outage_s`` later on its port.
    Searches in flight wait (the controller's outage budget must be longer than the outage);
    submissions meanwhile are refused with 503 and asked again. The window ends when the
    controller's ``/health`` says ok again."""
    if rig.supervised:
        raise ValueError("a supervisor would start the detector again at once")
    if _budget_s(rig) <= timing.outage_s:
        raise ValueError(
            f"an outage of {timing.outage_s:g} s needs an outage budget longer than it "
            f"(COSMOS_CONTROLLER_OUTAGE_BUDGET_S is {_budget_s(rig):g})"
        )
    with UnderLoad(rig, timing, "detector-outage", seed=2000, sentinel=True) as run:
        run.warm()
        down = run.begin()
        plans = [rig.kill(process) for process in rig.replicas("detector")]
        degraded_seen = False
        while time.monotonic() < down + timing.outage_s:
            health = rig.health() or {}
            if health.get("status") == "degraded" and "detector" in health["unavailable_stages"]:
                degraded_seen = True
            time.sleep(0.25)
        restarted = time.monotonic()
        for plan in plans:
            rig.restart(plan, timing.recover_s)
        wait_until(lambda: (rig.health() or {}).get("status") == "ok", timing.recover_s)
        back = run.end()
        measured = run.finish()
    in_flight = in_flight_at(run.outcomes, down)
    return DetectorOutage(
        measured,
        outage_s=restarted - down,
        degraded_seen=degraded_seen,
        recovered_after_s=back - restarted,
        in_flight=len(in_flight),
        ridden_out=sum(o.succeeded and (o.ended_at or 0.0) > restarted for o in in_flight),
    )


def controller_killed(rig: Rig, timing: Timing) -> ControllerKilled:
    """SIGKILL the controller mid-load; start it again on its port and database
    ``controller_down_s`` later. Its clients meanwhile get no answer and ask again; it resumes
    the queued and running searches from their recorded iterations. The window ends when it is
    healthy again."""
    if rig.supervised:
        raise ValueError("this scenario restarts the controller itself, not a supervisor")
    with UnderLoad(rig, timing, "controller-killed", seed=3000, sentinel=True) as run:
        run.warm()
        killed = run.begin()
        (controller,) = rig.replicas("controller")
        plan = rig.kill(controller)
        time.sleep(timing.controller_down_s)
        rig.restart(plan, timing.recover_s)
        back = run.end()
        measured = run.finish()
    in_flight = in_flight_at(run.outcomes, killed)
    known = {o.search_id for o in run.outcomes}
    orphans = {i: s for i, s in listed(rig.controller_url, run.key).items() if i not in known}
    return ControllerKilled(
        measured,
        down_s=back - killed,
        in_flight=len(in_flight),
        resumed=sum(o.succeeded and (o.ended_at or 0.0) > back for o in in_flight),
        orphans=len(orphans),
        orphans_unfinished=sum(s not in TERMINAL_STATUSES for s in orphans.values()),
    )


Scenario = Callable[[Rig, Timing], ScenarioResult]

SCENARIOS: Final[Mapping[str, Scenario]] = {
    "tenants": tenants,
    "replica-killed-supervised": replica_killed_supervised,
    "replica-killed-plain": replica_killed,
    "detector-outage": detector_outage,
    "controller-killed": controller_killed,
    "slow-clients": slow_clients,
    "maximal-uploads": maximal_uploads,
}
"""Every scenario by name, in the order they run on one stack (the uploads last: they leave the
most behind)."""


def run_scenarios(
    workdir: Path,
    timing: Timing,
    names: Sequence[str] | None = None,
    env: Mapping[str, str] | None = None,
) -> Iterator[ScenarioResult | ScenarioFailure]:
    """Run the scenarios ``names`` (all by default) in :data:`SCENARIOS`' order on one rig in
    ``workdir`` (with ``env``), yielding each result as it comes; a scenario that raises yields
    a :class:`ScenarioFailure` and the rest go on."""
    chosen = list(SCENARIOS) if names is None else list(names)
    unknown = [name for name in chosen if name not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenarios {unknown}: choose from {list(SCENARIOS)}")
    with fault_rig(workdir, env=env) as rig:
        for name in (name for name in SCENARIOS if name in chosen):
            try:
                yield SCENARIOS[name](rig, timing)
            except Exception as exc:  # one scenario's failure is its row, not the run's end
                yield ScenarioFailure(name, f"{type(exc).__name__}: {exc}")
