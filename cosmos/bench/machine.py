"""What ran the bench: the machine (CPU, cores, load, Python, platform) and the commit, for the
head of every report.
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = ["machine_info"]


def _cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else what :mod:`platform` says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git(*args: str) -> str:
    """The output of ``git <args>`` in this checkout."""
    return subprocess.run(
        ["git", *args],
        cwd=Path(__file__).resolve().parents[2],
        capture_output=True,
        text=True,
        check=True,
        timeout=10,
    ).stdout.strip()


def _git_commit() -> str:
    """HEAD's short hash, marked when tracked files differ from it (``unknown`` without git)."""
    try:
        head = _git("rev-parse", "--short", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + (" (with uncommitted changes)" if dirty else "")


def machine_info(services: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """What ran the bench: CPU, cores, load, Python, the commit, and what the services report."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return {
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "load_average_1m_at_start": round(load[0], 2),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "commit": _git_commit(),
        **dict(services or {}),
    }
