"""Lower the priority of Dr.Jit's worker threads, whose idle spin would slow the next stage.

After a kernel launch, Dr.Jit's thread pool (nanothread) workers busy-wait for several
milliseconds before they sleep. On a machine where the detector runs next to the renderer, that
spin takes a core from the detection of the view just rendered (measured here: a detection right
after a render took 7.1 ms instead of 5.5). At nice 19 the spin yields to any other runnable
thread, while a render that has the cores to itself runs as fast as before.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

__all__ = ["WORKER_NICE", "lower_worker_priority"]

_log = logging.getLogger("cosmos.renderer")
WORKER_NICE = 19
_WORKER_PREFIX = "nt ["  # how nanothread names its workers (``/proc/.../comm``)


def lower_worker_priority(nice: int = WORKER_NICE) -> int:
    """Set every Dr.Jit worker thread of this process to ``nice``; how many were found.

    Linux only (threads are found in ``/proc/self/task``); elsewhere, or when the pool has not
    started yet, it finds none. Raising a nice value needs no privileges.
    """
    if not sys.platform.startswith("linux"):
        return 0
    found = 0
    for task in Path("/proc/self/task").iterdir():
        try:
            if not (task / "comm").read_text().startswith(_WORKER_PREFIX):
                continue
            os.setpriority(os.PRIO_PROCESS, int(task.name), nice)
        except (OSError, ValueError):  # the thread ended meanwhile
            continue
        found += 1
    if found:
        _log.info("Dr.Jit worker threads: %d at nice %d", found, nice)
    return found
