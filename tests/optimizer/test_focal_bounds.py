"""The focal lengths a free search considers without the photo's intrinsics
(services.optimizer.free.focal_bounds): the lenses considered on a film, the zooms a fit may take
from its start, and when a fitted focal length ran into the bounds."""

from __future__ import annotations

import math

import pytest

from services.optimizer.free.focal_bounds import (
    AT_BOUND,
    FOCAL_BOUNDS,
    FULL_FRAME_DIAGONAL_MM,
    LENS_EQUIVALENT_MM,
    FocalRange,
    at_bound,
    zoom_bounds,
)

LOW, HIGH = FOCAL_BOUNDS


def _focal(fov_deg: float, width: float) -> float:
    return width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))


def test_a_drone_s_wide_lens_is_considered_whatever_the_scene_camera():
    """A scene modelled with a 30° camera; a drone's 24 mm-equivalent lens (84° across the
    diagonal) on a 4:3 photo: about 72° across, far beyond twice the scene camera's fov, and
    within the lenses considered."""
    width, height = 4000, 3000
    lenses = FocalRange.of(_focal(30.0, width), width, height)
    drone = 24.0 * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
    assert math.degrees(2.0 * math.atan(width / (2.0 * drone))) == pytest.approx(71.6, abs=0.1)
    assert drone < LOW * _focal(30.0, width)  # beyond the scene camera's own bounds
    assert lenses.low < drone < lenses.high
    widest, narrowest = lenses.fov_deg(width)
    assert widest == pytest.approx(106.2, abs=0.1)  # 13 mm on this film
    assert narrowest == pytest.approx(15.2, abs=0.1)  # twice the scene camera's focal length


def test_the_lenses_are_the_same_on_an_upright_photo():
    """The 35 mm equivalence counts along the diagonal: turning the film does not change it."""
    across = FocalRange.of(1000.0, 4000, 3000)
    upright = FocalRange.of(1000.0, 3000, 4000)
    assert (upright.low, upright.high) == pytest.approx((across.low, across.high))


def test_a_scene_camera_outside_the_lenses_keeps_its_own_bounds():
    """A scene camera narrower than the narrowest lens considered: its own bounds about it stay
    (a photo taken as the scene was modelled is still estimated)."""
    width, height = 640, 480
    per_mm = math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
    tele = 4.0 * LENS_EQUIVALENT_MM[1] * per_mm
    lenses = FocalRange.of(tele, width, height)
    assert lenses.low == pytest.approx(LENS_EQUIVALENT_MM[0] * per_mm)
    assert lenses.high == pytest.approx(HIGH * tele)


@pytest.mark.parametrize(
    ("start", "expected"),
    [
        (1.0, (LOW, HIGH)),  # at the scene camera's: the bounds themselves
        (1.5, (LOW / 1.5, HIGH / 1.5)),  # a start longer than it: the high bound nearer
        (0.6, (LOW / 0.6, HIGH / 0.6)),
    ],
)
def test_the_zooms_of_a_start_reach_the_bounds_whatever_the_start(start, expected):
    reference = 400.0
    low, high = zoom_bounds(start * reference, FocalRange.about(reference))
    assert (low, high) == pytest.approx(expected)
    assert low * start == pytest.approx(LOW)
    assert high * start == pytest.approx(HIGH)


def test_a_start_beyond_the_bounds_may_stay_but_not_go_further_out():
    reference = 400.0
    low, high = zoom_bounds(3.0 * reference, FocalRange.about(reference))
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
    assert at_bound(zoom * 500.0, FocalRange.about(500.0)) is ran_into
