"""The focal lengths a free search considers without the photo's intrinsics
(services.optimizer.free.focal_bounds): the zooms a fit may take from its start, and when a
fitted focal length ran into the bounds."""

from __future__ import annotations

import math

import pytest

from services.optimizer.free.focal_bounds import AT_BOUND, FOCAL_BOUNDS, at_bound, zoom_bounds

LOW, HIGH = FOCAL_BOUNDS


@pytest.mark.parametrize(
    ("start", "expected"),
    [
        (1.0, (LOW, HIGH)),  # at the scene camera's: the bounds themselves
        (1.5, (LOW / 1.5, HIGH / 1.5)),  # a start longer than it: the high bound nearer
        (0.6, (LOW / 0.6, HIGH / 0.6)),
    ],
)
def test_the_zooms_of_a_start_reach_the_bounds_about_the_scene_camera(start, expected):
    reference = 400.0
    low, high = zoom_bounds(start * reference, reference)
    assert (low, high) == pytest.approx(expected)
    assert low * start == pytest.approx(LOW)
    assert high * start == pytest.approx(HIGH)


def test_a_start_beyond_the_bounds_may_stay_but_not_go_further_out():
    reference = 400.0
    low, high = zoom_bounds(3.0 * reference, reference)
    assert low == pytest.approx(LOW / 3.0)
    assert high == 1.0


@pytest.mark.parametrize(
    ("zoom", "ran_into"),
    [
        (1.0, False),
        (HIGH * math.exp(-2 * AT_BOUND), False),
        (HIGH, True),
        (HIGH * math.exp(-AT_BOUND / 2), True),
        (3.0, True),  # beyond
        (LOW * math.exp(2 * AT_BOUND), False),
        (LOW, True),
        (0.2, True),
    ],
)
def test_a_focal_length_on_or_beyond_a_bound_ran_into_it(zoom, ran_into):
    assert at_bound(zoom * 500.0, 500.0) is ran_into
