"""The fault harness's own arithmetic: the nearest-rank p95, what counts as submitted,
succeeded and lost, which latencies fall in a fault's window, the memory read from /proc; and
the uploads scenario's body and what it takes for a good answer."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import cv2
import httpx
import numpy as np
import pytest

from cosmos.bench.faults.clients import maximal_upload_body, well_answered
from cosmos.bench.faults.harness import (
    MIB,
    Outcome,
    RssSampler,
    count,
    latencies,
    p95,
    percentile,
)
from cosmos.bench.memory import memory_of
from cosmos.bench.target import Target
from services.common.geometry.pose import GridIndex, Pose
from services.common.images import decode_image


def test_p95_is_the_nearest_rank():
    assert p95([]) is None
    assert p95([3.0]) == 3.0
    assert p95(range(1, 21)) == 19  # ⌈0.95 · 20⌉ = 19th of 20
    assert p95(range(1, 101)) == 95
    assert p95(range(1, 102)) == 96  # ⌈95.95⌉ = 96
    assert p95([5.0, 1.0, 4.0, 2.0, 3.0]) == 5.0  # ⌈4.75⌉ = 5th: unsorted input is sorted
    assert percentile([1, 2, 3, 4], 50) == 2
    assert percentile([1, 2, 3, 4], 100) == 4
    assert percentile([7, 1], 1) == 1
    with pytest.raises(ValueError, match="q must be"):
        percentile([1.0], 0)


def done(status: str, start: float = 0.0, end: float = 1.0, **extra) -> Outcome:
    return Outcome(start, f"s{start}-{status}", ended_at=end, status=status, **extra)


def test_counts_say_what_was_submitted_succeeded_and_lost():
    outcomes = [
        done("succeeded", correct=True),
        done("succeeded", 1.0, 2.0, correct=False, refusals=2),  # answered, elsewhere
        done("failed", error="urn:cosmos:problem:stage-unavailable"),
        done("cancelled"),
        Outcome(0.0, "s-running", status="running"),  # never seen to end
        Outcome(0.0, "s-gone", ended_at=1.0, status="vanished"),  # its GET said 404
        Outcome(0.0, ended_at=1.0, status="rejected", error="500: boom"),  # refused for good
        Outcome(0.0, refusals=3),  # still refused (503) when the load stopped: not submitted
        Outcome(0.0, unanswered=1),  # no answer, then the load stopped: not submitted
        Outcome(0.0, "s-again", ended_at=3.0, status="succeeded", unanswered=2),
    ]
    counts = count(outcomes)
    assert counts.submitted == 8
    assert counts.succeeded == 3
    assert counts.lost == 5 == counts.submitted - counts.succeeded
    assert counts.unfinished == 1
    assert counts.failed == 4
    assert counts.refused == 1
    assert counts.refusals == 5
    assert counts.unanswered == 3
    assert counts.wrong_pose == 1
    assert count([]).submitted == count([]).lost == 0


def test_latency_runs_from_the_first_attempt_and_the_window_takes_overlapping_searches():
    outcomes = [
        done("succeeded", 0.0, 1.0),  # ended before the window
        done("succeeded", 1.5, 4.0),  # began before it, ended in it
        done("succeeded", 3.0, 3.5),  # inside
        done("succeeded", 5.5, 9.0),  # began in it
        done("succeeded", 6.5, 7.0),  # after it
        done("failed", 3.0, 4.0),  # no latency: lost
        Outcome(3.0, "s-open", status="running"),  # never ended: no latency
    ]
    assert latencies(outcomes) == [1.0, 2.5, 0.5, 3.5, 0.5]
    assert latencies(outcomes, (2.0, 6.0)) == [2.5, 0.5, 3.5]
    assert outcomes[-1].overlaps(100.0, 200.0)  # an open life overlaps every later window
    assert not outcomes[0].overlaps(1.01, 2.0)
    assert outcomes[0].overlaps(1.0, 2.0)  # the ends touch


def test_memory_is_read_from_proc_and_the_peak_counts_from_the_start():
    """A child that allocates 200 MiB and frees it before the sampler starts: its high-water
    mark is started over, so the peak is what it holds then, not the old 200 MiB; allocating
    again afterwards is seen."""
    with subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "a = bytearray(200 * 2**20); del a\n"
            "print('freed', flush=True); sys.stdin.readline()\n"
            "b = bytearray(100 * 2**20)\n"
            "for i in range(0, len(b), 4096): b[i] = 1\n"
            "print('held', flush=True); sys.stdin.readline()\n",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    ) as child:
        assert child.stdin is not None
        assert child.stdout is not None
        try:
            assert child.stdout.readline().strip() == "freed"
            memory = memory_of(child.pid)
            assert memory is not None
            rss, hwm = memory
            assert hwm >= 200 * MIB > rss
            sampler = RssSampler(lambda: [("child", child.pid)], interval_s=0.05).start()
            assert sampler.peaks_mib["child"] < 100
            child.stdin.write("\n")
            child.stdin.flush()
            assert child.stdout.readline().strip() == "held"
            time.sleep(0.2)
            peaks = sampler.stop()
            assert 100 <= peaks["child"] < 200
        finally:
            child.kill()
            child.wait()
    assert memory_of(child.pid) is None
    assert memory_of(os.getpid()) is not None


def test_a_maximal_upload_is_a_valid_image_just_under_the_limit():
    ok, png = cv2.imencode(".png", np.full((240, 320, 3), 90, np.uint8))
    assert ok
    target = Target(
        "demo", png.tobytes(), GridIndex(lat=0, lon=0), Pose(theta_deg=0.0, phi_deg=0.0)
    )
    limit = 20 * MIB
    body = maximal_upload_body(target, limit, max_pixels=4096 * 4096, max_side=8192)
    assert limit - 16 * 1024 < len(body) <= limit
    image = decode_image(body, max_pixels=4096 * 4096, max_side=8192)
    height, width = image.shape[:2]
    assert abs(width / height - 4 / 3) < 0.01  # the target's aspect
    assert len(body) == len(b"P6\n%d %d\n255\n" % (width, height)) + 3 * width * height
    capped = maximal_upload_body(target, limit, max_pixels=1000 * 750, max_side=8192)
    assert decode_image(capped, max_pixels=10**6, max_side=8192).shape[:2] == (750, 1000)


@pytest.mark.parametrize(
    ("status", "headers", "good"),
    [
        (202, {"content-type": "application/json"}, True),
        (413, {"content-type": "application/problem+json"}, True),
        (413, {"content-type": "text/plain"}, False),  # not a problem
        (429, {"content-type": "application/problem+json", "retry-after": "5"}, True),
        (429, {"content-type": "application/problem+json"}, False),  # no Retry-After
        (503, {"content-type": "application/problem+json", "retry-after": "5"}, True),
        (503, {"content-type": "application/problem+json"}, False),
        (500, {"content-type": "application/problem+json"}, False),
        (200, {"content-type": "application/json"}, False),  # a search is taken with 202
    ],
)
def test_what_counts_as_a_good_answer_to_an_upload(status, headers, good):
    assert well_answered(httpx.Response(status, headers=headers)) is good
