"""The one process-memory reader (:mod:`cosmos.bench.memory`): this process's memory, named."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from cosmos.bench.memory import memory_of, reset_peak

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def test_a_live_process_has_resident_memory_at_most_its_peak():
    memory = memory_of(os.getpid())
    assert memory is not None
    assert 0 < memory.rss_bytes <= memory.peak_bytes
    assert tuple(memory) == (memory.rss_bytes, memory.peak_bytes)


def test_a_gone_process_has_none():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    assert memory_of(child.pid) is None
    assert reset_peak(child.pid) is False
