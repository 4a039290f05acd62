"""The evaluation of COSMOS 3D Search through its real services (``cosmos bench``).

:mod:`.variants` makes the target images (:mod:`.altered` the modified scene copies that
``photo`` and ``changed`` targets are rendered from), :mod:`.runner` runs searches over HTTP and
records them (:mod:`.traces` explains the misses). :mod:`.stats` summarises the records (paper
eq. 9 too), :mod:`.tables` lays them out, :mod:`.plots` draws them, :mod:`.machine` says what ran
them and :mod:`.results_md` writes ``docs/RESULTS.md`` from the JSON reports. :mod:`.profile`
measures a search's floor in one process, :mod:`.settings_sweep` the render settings
(:mod:`.settings_choice` picks one), :mod:`.scenes` generates random scenes that
:mod:`.random_run` searches with the general and the per-scene detector (:mod:`.random_report`
its figures); :mod:`.session` is what the command's modes share and :mod:`.command` runs them.
:mod:`.faults` is the fault suite (``python -m benchmarks.faults``, ``tests/faults/``);
:mod:`.free_targets` draws free-camera targets with the baseline and the box-only bound they are
measured against (``python -m cosmos.bench.free_targets``; issue 23, item 5); :mod:`.free_run`
searches them through the stack (``cosmos bench --free``, figures in :mod:`.free_bench`).
"""

from cosmos.bench.command import run
from cosmos.bench.runner import BenchTarget, SearchRecord
from cosmos.bench.session import BenchConfig
from cosmos.bench.target import Target
from cosmos.bench.variants import VARIANTS, Variant

__all__ = ["VARIANTS", "BenchConfig", "BenchTarget", "SearchRecord", "Target", "Variant", "run"]
