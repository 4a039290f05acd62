"""The evaluation of COSMOS 3D Search through its real services (``cosmos bench``).

:mod:`.variants` makes the target images, :mod:`.runner` runs searches over HTTP and records
them, :mod:`.report` turns records into tables, plots and ``docs/RESULTS.md``, :mod:`.profile`
measures a search's floor in one process, :mod:`.settings_sweep` the render settings, and
:mod:`.command` ties them into the command's modes.
"""

from services.bench.command import BenchConfig, run
from services.bench.runner import SearchRecord, Target
from services.bench.variants import VARIANTS, Variant

__all__ = ["VARIANTS", "BenchConfig", "SearchRecord", "Target", "Variant", "run"]
