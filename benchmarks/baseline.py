"""A benchmark's measurement at an earlier commit, for a before-and-after in one run.

:func:`measure_at` extracts git ``ref``'s tree (``git archive``) into a temporary directory,
copies the running benchmark's own file and this one into it (so the older code is measured the
same way),
and runs ``python -m benchmarks.<name> <argv>`` there (``argv`` asks for one measurement, e.g.
with ``--worker``); the child prints its result as one JSON line last, which is returned.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["describe", "measure_at"]

ROOT = Path(__file__).resolve().parents[1]


def measure_at(ref: str, benchmark: Path, argv: list[str]) -> dict[str, Any]:
    """The JSON result of the benchmark whose file is ``benchmark``, run with ``argv`` on
    ``ref``'s tree, in a child process."""
    with tempfile.TemporaryDirectory() as tree:
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", ref], check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", tree], input=archive, check=True)
        for own in (benchmark, Path(__file__)):  # the benchmark measures as it does now
            shutil.copy(own, Path(tree) / "benchmarks" / own.name)
        child = subprocess.run(
            [sys.executable, "-m", f"benchmarks.{benchmark.stem}", *argv],
            cwd=tree,
            capture_output=True,
            text=True,
        )
        if child.returncode != 0:
            raise RuntimeError(f"the {ref} measurement failed:\n{child.stderr[-4000:]}")
        result: dict[str, Any] = json.loads(child.stdout.strip().splitlines()[-1])
        return result


def describe(ref: str) -> str:
    """``ref`` and the commit it names."""
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", ref],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return ref if ref == commit else f"{ref} {commit}"
