"""The upload benchmark (:mod:`benchmarks.upload_pieces`) runs both ways against its sink
process, every upload answered, and reports them with their ratios (its figures are the
benchmark's, not asserted here)."""

from __future__ import annotations

from benchmarks.upload_pieces import measure, report


def test_both_ways_are_measured_and_every_upload_answered():
    ways = measure(uploads=4, mib=2.0, hold_s=0.2)
    assert [w.name for w in ways] == ["whole", "in pieces"]
    for way in ways:
        assert way.answered == way.uploads == 4
        assert way.cpu_s > 0
        assert 0 <= way.last_head_s < way.wall_s
    text = report(ways)
    assert "whole / in pieces: client CPU" in text
