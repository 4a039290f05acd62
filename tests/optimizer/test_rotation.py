"""The longitude solve (closed-form 2-D rotation fit): property tests against brute force,
equivariance, invariances and degenerate input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services.optimizer.geometry import ground_offsets, rotate2d, world_from_offsets
from services.optimizer.longitude import solve_rotation

angles = st.floats(-720.0, 720.0, allow_nan=False)
clouds = hnp.arrays(
    np.float64,
    st.tuples(st.integers(1, 8), st.just(2)),
    elements=st.floats(-5.0, 5.0, allow_nan=False),
)
weights = st.floats(0.01, 100.0)


def circular_gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def spread(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(points, axis=1)))


@settings(max_examples=150, deadline=None)
@given(points=clouds, phi=angles)
def test_recovers_the_rotation_of_exact_pairs(points, phi):
    assume(spread(points) > 1e-3)
    fit = solve_rotation(points, rotate2d(points, phi))
    assert fit.determined
    assert circular_gap(fit.phi_deg, phi % 360.0) < 1e-6
    assert fit.rms == pytest.approx(0.0, abs=1e-6)
    assert fit.coherence == pytest.approx(1.0, abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(
    points=clouds,
    phi=angles,
    psi=angles,
    noise=hnp.arrays(np.float64, (8, 2), elements=st.floats(-0.5, 0.5)),
)
def test_rotating_the_world_rotates_the_estimate(points, phi, psi, noise):
    """Metamorphic: turn every world position by ψ and the estimate turns by ψ."""
    world = rotate2d(points, phi) + noise[: len(points)]
    assume(spread(points) > 1e-2 and spread(world) > 1e-2)
    first = solve_rotation(points, world)
    turned = solve_rotation(points, rotate2d(world, psi))
    assume(first.determined and first.coherence > 1e-3)
    assert circular_gap(turned.phi_deg, first.phi_deg + psi) < 1e-6
    assert turned.rms == pytest.approx(first.rms, rel=1e-6, abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(
    points=clouds,
    phi=angles,
    scale=weights,
    noise=hnp.arrays(np.float64, (8, 2), elements=st.floats(-0.5, 0.5)),
    data=st.data(),
)
def test_matches_brute_force_and_ignores_order_and_weight_scale(points, phi, scale, noise, data):
    world = rotate2d(points, phi) + noise[: len(points)]
    w = np.array(data.draw(st.lists(weights, min_size=len(points), max_size=len(points))))
    fit = solve_rotation(points, world, w)
    assume(fit.determined and fit.coherence > 1e-3)
    grid = np.linspace(0.0, 360.0, 36001)
    residual = [np.sum(w * np.sum((world - rotate2d(points, a)) ** 2, axis=1)) for a in grid[::100]]
    coarse = grid[::100][int(np.argmin(residual))]
    fine = grid[(np.abs(grid - coarse) <= 1.0) | (np.abs(grid - coarse) >= 359.0)]
    energy = [np.sum(w * np.sum((world - rotate2d(points, a)) ** 2, axis=1)) for a in fine]
    best = fine[int(np.argmin(energy))]
    closed = np.sum(w * np.sum((world - rotate2d(points, fit.phi_deg)) ** 2, axis=1))
    assert closed <= min(energy) + 1e-9  # the closed form is at least as good as any sample
    assert circular_gap(fit.phi_deg, best) < 0.02 or closed == pytest.approx(min(energy))
    order = data.draw(st.permutations(range(len(points))))
    again = solve_rotation(points[order], world[order], w[order] * scale)
    assert circular_gap(again.phi_deg, fit.phi_deg) < 1e-7
    assert again.rms == pytest.approx(fit.rms, rel=1e-6, abs=1e-9)


def test_noise_raises_the_residual_smoothly():
    rng = np.random.default_rng(3)
    points = rng.uniform(-3, 3, (6, 2))
    clean = rotate2d(points, 40.0)
    direction = rng.normal(size=clean.shape)
    residuals = [solve_rotation(points, clean + s * direction).rms for s in (0.0, 0.01, 0.1, 0.3)]
    errors = [
        circular_gap(solve_rotation(points, clean + s * direction).phi_deg, 40.0)
        for s in (0.0, 0.01, 0.1, 0.3)
    ]
    assert residuals == sorted(residuals)
    assert residuals[0] == pytest.approx(0.0, abs=1e-9)
    assert errors[0] < 1e-9
    assert errors[1] < 1.0
    assert errors == sorted(errors)


@pytest.mark.parametrize(
    ("offsets", "positions"),
    [
        (np.zeros((0, 2)), np.zeros((0, 2))),
        (np.zeros((3, 2)), np.ones((3, 2))),
        ([[np.nan, 1.0]], [[1.0, 0.0]]),
    ],
)
def test_degenerate_pairs_leave_the_angle_undetermined(offsets, positions):
    fit = solve_rotation(offsets, positions)
    assert not fit.determined
    assert fit.coherence == 0.0


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="must match"):
        solve_rotation(np.zeros((2, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="non-negative"):
        solve_rotation(np.ones((2, 2)), np.ones((2, 2)), [1.0, -1.0])


@settings(max_examples=100, deadline=None)
@given(points=clouds, phi=angles)
def test_eq7_offsets_and_world_positions_are_inverse_rotations(points, phi):
    assert np.allclose(ground_offsets(world_from_offsets(points, phi), phi), points, atol=1e-9)
    # e1 = (cos φ, sin φ) points at the camera's foot: offset (1, 0) lands there.
    foot = world_from_offsets([1.0, 0.0], phi)
    assert foot == pytest.approx([math.cos(math.radians(phi)), math.sin(math.radians(phi))])


def test_tiny_points_give_the_same_answer_at_any_weight_scale():
    """Points of 1e-155 (found by Hypothesis): their products underflowed to subnormals, so the
    weights' scale decided whether the rotation was determined (NaN at weight 1/1600)."""
    points = np.array([[2.62277337e-155, 0.0], [0.0, 1.3e-155]])
    world = rotate2d(points, 30.0)
    for w in (np.ones(2), np.full(2, 0.01 * 0.0625), np.full(2, 64.0)):
        fit = solve_rotation(points, world, w)
        assert fit.determined
        assert circular_gap(fit.phi_deg, 30.0) < 1e-9
