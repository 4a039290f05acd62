"""A process's memory as Linux reports it in ``/proc``: the one process-memory reader.

:func:`memory_of` reads the resident size now and its high-water mark (``VmRSS`` and ``VmHWM`` of
``/proc/<pid>/status``); :func:`reset_peak` starts that mark over. The fault suite's memory
sampler and the tests read memory through these two.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

__all__ = ["ProcessMemory", "memory_of", "reset_peak"]


class ProcessMemory(NamedTuple):
    """A process's resident memory, in bytes."""

    rss_bytes: int
    """Resident now (``VmRSS``)."""
    peak_bytes: int
    """The most resident since the process started or :func:`reset_peak` (``VmHWM``)."""


def memory_of(pid: int) -> ProcessMemory | None:
    """The process's resident memory now and its high-water mark (:class:`ProcessMemory`);
    None once it is gone, or where ``/proc`` does not say (not Linux)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return None
    fields = {}
    for line in lines:
        name, _, value = line.partition(":")
        if name in {"VmRSS", "VmHWM"}:
            fields[name] = int(value.split()[0]) * 1024  # kB
    if len(fields) < 2:  # a zombie has no memory left
        return None
    return ProcessMemory(fields["VmRSS"], fields["VmHWM"])


def reset_peak(pid: int) -> bool:
    """Start the process's ``VmHWM`` over from its current RSS (``clear_refs`` 5, Linux ≥ 4.0);
    False where that is not allowed."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        return False
    return True
