"""``cosmos bench --free``: free-camera targets (issue 23, item 5) searched through the real
stack, beside the plain ``solvePnPRansac`` baseline and the ideal box-only bound.

:mod:`.targets` makes each target's image per variant, :mod:`.searching` searches it and times
its floor, :mod:`.baseline` is the baseline on the detector's boxes, :mod:`.records` what is kept
of each search, :mod:`.checkpoint` lets a run resume, :mod:`.report` its tables and goals;
:mod:`cosmos.bench.free_run` runs it all.
"""

from cosmos.bench.free_bench.records import METHODS, CameraRecord, FreeRecord

__all__ = ["METHODS", "CameraRecord", "FreeRecord"]
