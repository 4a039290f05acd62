"""The fault suite of issue 15: normal searches under load while a fault strikes the real
processes of a local stack, counted (submitted, succeeded, lost), with each service's peak
memory and the p95 latency during the fault.

:mod:`.harness` measures (the load, the memory sampler, counts and p95), :mod:`.rig` holds the
stack under fault (kill, restart, keys, targets), :mod:`.scenarios` injects the faults, one
function each. ``python -m benchmarks.faults`` runs them and prints the table;
``tests/faults/`` asserts on them.
"""

from cosmos.bench.faults.harness import Counts, Load, Outcome, RssSampler, count, p95
from cosmos.bench.faults.rig import Rig, fault_rig
from cosmos.bench.faults.scenarios import (
    SCENARIOS,
    ScenarioFailure,
    ScenarioResult,
    Timing,
    run_scenarios,
)

__all__ = [
    "SCENARIOS",
    "Counts",
    "Load",
    "Outcome",
    "Rig",
    "RssSampler",
    "ScenarioFailure",
    "ScenarioResult",
    "Timing",
    "count",
    "fault_rig",
    "p95",
    "run_scenarios",
]
