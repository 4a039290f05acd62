"""The fault suite of issue 15: normal searches under load while a fault strikes the real
processes of a local stack, counted (submitted, succeeded, lost), with each service's peak
memory and the p95 latency during the fault.

:mod:`.harness` measures (the load, the memory sampler, counts and p95), :mod:`.rig` holds the
stack under fault (kill, restart, keys, targets), :mod:`.under_load` runs a scenario's load and
fault window, :mod:`.scenarios` (processes killed) and :mod:`.clients` (clients misbehaving)
inject the faults, one function each, and :mod:`.results` holds what each measured.
``python -m benchmarks.faults`` runs them and prints the table; ``tests/faults/`` asserts on
them.
"""

from cosmos.bench.faults.harness import Counts, Load, Outcome, RssSampler, count, p95
from cosmos.bench.faults.results import ScenarioFailure, ScenarioResult
from cosmos.bench.faults.rig import Rig, fault_rig
from cosmos.bench.faults.scenarios import SCENARIOS, run_scenarios
from cosmos.bench.faults.under_load import Timing

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
