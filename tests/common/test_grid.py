"""Tests of the camera hemisphere grid: ring sizes, conversions, indices, neighbours, nearest."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from services.common.geometry.grid import (
    MAX_GRID_SIZE,
    GridError,
    GridSpec,
    HemisphereGrid,
    grid_for,
)
from services.common.geometry.pose import GridIndex, Pose
from services.common.geometry.sphere import (
    angular_distance_deg,
    cartesian_to_pose,
    pose_to_cartesian,
)

DEMO = (7.5, 7.5, 82.5)
GRID_PARAMS = [
    DEMO,
    (7.5, 0.0, 90.0),
    (math.degrees(math.pi / 24), 0.0, 90.0),
    (90.0, 0.0, 90.0),
    (10.0, 5.0, 85.0),
    (13.0, 0.0, 90.0),
    (20.0, 30.0, 90.0),
]
grid_params = st.sampled_from(GRID_PARAMS)


def circular_diff_deg(a: float | np.ndarray, b: float | np.ndarray) -> np.ndarray:
    diff: np.ndarray = (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0
    return diff


@st.composite
def grid_and_index(draw):
    grid = grid_for(*draw(grid_params))
    lat = draw(st.integers(0, grid.ring_count - 1))
    lon = draw(st.integers(0, grid.ring_size(lat) - 1))
    return grid, GridIndex(lat=lat, lon=lon)


def min_separation_deg(grid: HemisphereGrid) -> float:
    dist = angular_distance_deg(
        (grid.theta_deg[:, None], grid.phi_deg[:, None]),
        (grid.theta_deg[None, :], grid.phi_deg[None, :]),
    )
    np.fill_diagonal(dist, np.inf)
    return float(dist.min())


# -- ring layout -------------------------------------------------------------------------------


def test_full_grid_at_7_5_degrees_has_pole_and_48_on_the_equator():
    grid = HemisphereGrid(7.5, 0.0, 90.0)
    counts = [ring.count for ring in grid.rings]
    assert counts == [1, 6, 12, 18, 24, 29, 34, 38, 42, 44, 46, 48, 48]
    assert [ring.theta_deg for ring in grid.rings] == [7.5 * k for k in range(13)]
    assert [ring.lat for ring in grid.rings] == list(range(13))
    assert grid.ring_count == 13
    assert grid.size == sum(counts) == 390
    assert grid.ring_size(0) == 1
    assert grid.ring_size(12) == 48


def test_demo_grid_has_eleven_rings_from_7_5_to_82_5():
    grid = grid_for(*DEMO)
    assert grid.ring_count == 11
    assert grid.rings[0].theta_deg == 7.5
    assert grid.rings[-1].theta_deg == 82.5  # the 1e-9 tolerance keeps the upper end
    assert grid.size == 341
    assert grid.pose(GridIndex(lat=0, lon=0)) == Pose(theta_deg=7.5, phi_deg=0.0)


def test_pi_over_24_step_includes_the_pole_and_the_equator():
    step = math.degrees(math.pi / 24)  # 7.499999999999999, not exactly 7.5
    grid = HemisphereGrid(step, 0.0, 90.0)
    assert grid.ring_count == 13
    assert grid.rings[0].theta_deg == 0.0
    assert grid.rings[0].count == 1
    assert grid.rings[-1].theta_deg == pytest.approx(90.0)
    assert grid.rings[-1].count == 48
    assert [r.count for r in grid.rings] == [r.count for r in HemisphereGrid(7.5).rings]


def test_coarsest_grid_is_pole_and_four_equator_positions():
    grid = HemisphereGrid(90.0)
    assert [(r.theta_deg, r.count) for r in grid.rings] == [(0.0, 1), (90.0, 4)]
    assert grid.phi_deg.tolist() == [0.0, 0.0, 90.0, 180.0, 270.0]


def test_ring_sizes_round_half_up():
    # This step makes 360·sin(Δ)/Δ exactly 4.5 in floating point: banker's rounding would give 4.
    step = 78.35271869390664
    assert 360.0 * math.sin(math.radians(step)) / step == 4.5
    assert HemisphereGrid(step, step, step).rings[0].count == 5


def test_range_ends_survive_floating_point_error():
    # 0.3 / 0.1 == 2.9999999999999996, and (90/169)·169 == 90.00000000000001.
    assert [r.theta_deg for r in HemisphereGrid(0.1, 0.3, 0.3).rings] == [pytest.approx(0.3)]
    equator = HemisphereGrid(90.0 / 169.0, 90.0, 90.0).rings
    assert [(r.theta_deg, r.count) for r in equator] == [(90.0, 676)]


@settings(max_examples=60, deadline=None)
@given(
    step=st.floats(1.0, 90.0),
    lo=st.floats(0.0, 90.0),
    hi=st.floats(0.0, 90.0),
)
def test_rings_are_multiples_of_the_step_and_spaced_by_it_along_the_ring(step, lo, hi):
    lo, hi = min(lo, hi), max(lo, hi)
    assume(math.floor(hi / step) >= math.ceil(lo / step))
    grid = HemisphereGrid(step, lo, hi)
    thetas = np.array([r.theta_deg for r in grid.rings])
    k = np.round(thetas / step)
    np.testing.assert_allclose(thetas, k * step)
    np.testing.assert_array_equal(np.diff(k), 1.0)
    assert thetas[0] >= lo - 1e-9
    assert thetas[-1] <= hi + 1e-9
    # No ring is missing at either end.
    assert thetas[0] - step < lo - 1e-9 or thetas[0] == 0.0
    assert thetas[-1] + step > hi + 1e-9
    for ring in grid.rings:
        if ring.theta_deg == 0.0:
            assert ring.count == 1
            continue
        # n = round(360 sinθ / Δ) means the arc between positions is within Δ/(2n) of Δ.
        arc = 360.0 * math.sin(math.radians(ring.theta_deg)) / ring.count
        assert abs(arc - step) <= step / (2 * ring.count) + 1e-9
    assert grid.size == sum(r.count for r in grid.rings)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((0.0, 0.0, 90.0), "angle_step_deg"),
        ((-7.5, 0.0, 90.0), "angle_step_deg"),
        ((90.5, 0.0, 90.0), "angle_step_deg"),
        ((math.nan, 0.0, 90.0), "angle_step_deg"),
        ((math.inf, 0.0, 90.0), "angle_step_deg"),
        ((7.5, -1.0, 90.0), "min_theta_deg"),
        ((7.5, 0.0, 91.0), "max_theta_deg"),
        ((7.5, 50.0, 40.0), "min_theta_deg <= max_theta_deg"),
        ((7.5, math.nan, 90.0), "min_theta_deg"),
        ((50.0, 10.0, 40.0), "no ring"),
        ((7.5, 8.0, 14.0), "no ring"),
        ((0.01, 0.0, 90.0), "more than"),
    ],
)
def test_invalid_grids_raise_clear_errors(args, message):
    with pytest.raises(ValueError, match=message):
        HemisphereGrid(*args)


def test_grids_are_cached_hashable_and_compared_by_parameters():
    assert grid_for(*DEMO) is grid_for(*DEMO)
    assert HemisphereGrid(7.5) == HemisphereGrid(7.5, 0.0, 90.0)
    assert hash(HemisphereGrid(7.5)) == hash(HemisphereGrid(7.5, 0, 90))
    assert HemisphereGrid(7.5) != grid_for(*DEMO)
    assert len({HemisphereGrid(7.5), HemisphereGrid(7.5), grid_for(*DEMO)}) == 2


def test_the_spec_describes_the_grid_and_round_trips():
    grid = grid_for(*DEMO)
    spec = grid.spec()
    assert (spec.angle_step_deg, spec.min_theta_deg, spec.max_theta_deg) == DEMO
    again = GridSpec.model_validate_json(spec.model_dump_json())
    assert again == spec
    assert again.grid() is grid


# -- conversions -------------------------------------------------------------------------------


def test_pose_to_cartesian_known_values():
    np.testing.assert_allclose(pose_to_cartesian(0.0, 123.0), [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(pose_to_cartesian(90.0, 0.0, 2.0), [2.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(pose_to_cartesian(90.0, 90.0), [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(
        pose_to_cartesian(60.0, 225.0, 4.0),
        [-4 * math.sqrt(3) / 2 / math.sqrt(2), -4 * math.sqrt(3) / 2 / math.sqrt(2), 2.0],
    )


def test_conversions_broadcast():
    xyz = pose_to_cartesian(np.array([[10.0], [20.0]]), np.array([0.0, 90.0, 180.0]), 3.0)
    assert xyz.shape == (2, 3, 3)
    theta, phi, radius = cartesian_to_pose(xyz)
    assert theta.shape == phi.shape == radius.shape == (2, 3)
    np.testing.assert_allclose(radius, 3.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        cartesian_to_pose(np.zeros((4, 2)))


def test_cartesian_to_pose_pins_phi_on_the_axis_and_wraps_into_range():
    theta, phi, radius = cartesian_to_pose([[-0.0, 0.0, 2.0], [0.0, -0.0, -1.0], [0.0, 0.0, 0.0]])
    assert theta.tolist() == [0.0, 180.0, 0.0]
    assert phi.tolist() == [0.0, 0.0, 0.0]
    assert radius.tolist() == [2.0, 1.0, 0.0]
    _, phi, _ = cartesian_to_pose([[1.0, -1e-300, 0.0], [1.0, -1.0, 0.0], [-1.0, -0.0, 0.0]])
    assert np.all((phi >= 0.0) & (phi < 360.0))
    assert phi[1] == pytest.approx(315.0)
    assert phi[2] == pytest.approx(180.0)


@given(
    theta=st.floats(0.0, 180.0),
    phi=st.floats(0.0, 360.0, exclude_max=True),
    radius=st.floats(1e-3, 1e3),
)
def test_pose_cartesian_round_trip(theta, phi, radius):
    theta2, phi2, radius2 = cartesian_to_pose(pose_to_cartesian(theta, phi, radius))
    assert float(theta2) == pytest.approx(theta, abs=1e-9)
    assert float(radius2) == pytest.approx(radius, rel=1e-12)
    assert 0.0 <= float(phi2) < 360.0
    if 1e-6 < theta < 180.0 - 1e-6:
        assert abs(circular_diff_deg(phi2, phi)) < 1e-6


def test_angular_distance_known_values_and_symmetry():
    zenith, east = Pose(theta_deg=0.0, phi_deg=0.0), Pose(theta_deg=90.0, phi_deg=0.0)
    assert float(angular_distance_deg(zenith, east)) == pytest.approx(90.0)
    assert float(angular_distance_deg(east, (90.0, 180.0))) == pytest.approx(180.0)
    assert float(angular_distance_deg(zenith, (0.0, 200.0))) == 0.0  # φ is moot at the pole
    assert float(angular_distance_deg((45.0, 10.0), (45.0, 370.0))) == pytest.approx(0.0, abs=1e-12)
    a = (np.array([10.0, 50.0, 80.0]), np.array([0.0, 100.0, 300.0]))
    b = (np.array([[20.0], [70.0]]), np.array([[350.0], [30.0]]))
    dist = angular_distance_deg(a, b)
    assert dist.shape == (2, 3)
    np.testing.assert_allclose(dist, angular_distance_deg(b, a))


def test_angular_distance_is_accurate_for_nearly_equal_directions():
    # arccos(a·b) cannot resolve 1e-7° (1 - cos is below float resolution); atan2 can.
    assert float(angular_distance_deg((45.0, 0.0), (45.0 + 1e-7, 0.0))) == pytest.approx(
        1e-7, rel=1e-6
    )


@given(
    t1=st.floats(0.0, 180.0),
    p1=st.floats(-720.0, 720.0),
    t2=st.floats(0.0, 180.0),
    p2=st.floats(-720.0, 720.0),
)
def test_angular_distance_matches_arccos_of_the_dot_product(t1, p1, t2, p2):
    dot = float(np.dot(pose_to_cartesian(t1, p1), pose_to_cartesian(t2, p2)))
    expected = math.degrees(math.acos(min(1.0, max(-1.0, dot))))
    assert float(angular_distance_deg((t1, p1), (t2, p2))) == pytest.approx(expected, abs=1e-5)


# -- indices -----------------------------------------------------------------------------------


@pytest.mark.parametrize("params", GRID_PARAMS)
def test_every_index_round_trips_through_pose_and_flat(params):
    grid = grid_for(*params)
    indices = grid.all_indices()
    assert len(indices) == grid.size == len(set(indices))
    assert [i.lat for i in indices] == sorted(i.lat for i in indices)  # lat-major
    for i, index in enumerate(indices):
        assert grid.contains(index)
        assert grid.flat(index) == i
        assert grid.unflat(i) == index
        pose = grid.pose(index)
        assert grid.index_of(pose) == index
        assert (pose.theta_deg, pose.phi_deg) == (grid.theta_deg[i], grid.phi_deg[i])
        n = grid.ring_size(index.lat)
        assert pose.phi_deg == pytest.approx(index.lon * 360.0 / n)
        assert pose.theta_deg == grid.rings[index.lat].theta_deg


def test_pose_arrays_are_read_only():
    grid = grid_for(*DEMO)
    with pytest.raises(ValueError, match="read-only"):
        grid.theta_deg[0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        grid.phi_deg[0] = 1.0


def test_index_of_accepts_tiny_errors_and_wraps_phi():
    grid = HemisphereGrid(7.5)
    assert grid.index_of(Pose(theta_deg=90.0 - 1e-8, phi_deg=360.0 - 1e-8)) == GridIndex(
        lat=12, lon=0
    )
    assert grid.index_of(Pose(theta_deg=90.0, phi_deg=-7.5)) == GridIndex(lat=12, lon=47)
    assert grid.index_of(Pose(theta_deg=90.0, phi_deg=720.0 + 15.0)) == GridIndex(lat=12, lon=2)
    # Every azimuth at the pole is the same view, so the pole ring ignores φ.
    assert grid.index_of(Pose(theta_deg=0.0, phi_deg=123.0)) == GridIndex(lat=0, lon=0)


@pytest.mark.parametrize(
    ("theta", "phi", "message"),
    [
        (10.0, 0.0, "θ = 10° is not a ring"),
        (7.5 + 1e-4, 0.0, "not a ring"),
        (0.0, 0.0, "not a ring"),  # the demo grid has no pole
        (90.0, 0.0, "not a ring"),
        (82.5, 3.0, "φ = 3° is not a position of ring lat=10"),
        (82.5, 7.5 + 1e-4, "not a position"),
        (82.5, 7.5 - 1e-4, "not a position"),
    ],
)
def test_index_of_rejects_off_grid_poses(theta, phi, message):
    grid = grid_for(*DEMO)
    with pytest.raises(GridError, match=message):
        grid.index_of(Pose(theta_deg=theta, phi_deg=phi))


@pytest.mark.parametrize(
    ("lat", "lon", "message"),
    [
        (11, 0, r"lat 11 is out of range: valid rings are 0\.\.10"),
        (0, 6, r"lon 6 is out of range for ring lat=0 \(θ = 7\.5°\): valid positions are 0\.\.5"),
        (10, 48, r"lon 48 .* 0\.\.47"),
    ],
)
def test_invalid_indices_raise_naming_the_bad_coordinate(lat, lon, message):
    grid = grid_for(*DEMO)
    index = GridIndex(lat=lat, lon=lon)
    assert not grid.contains(index)
    for call in (grid.validate, grid.flat, grid.pose, grid.neighbours):
        with pytest.raises(GridError, match=message):
            call(index)
    with pytest.raises(GridError, match=message):
        grid.neighbour(index, "E")


def test_bad_flat_indices_and_rings_raise():
    grid = grid_for(*DEMO)
    assert issubclass(GridError, ValueError)
    for i in (-1, grid.size):
        with pytest.raises(GridError, match=r"flat index .* valid are 0\.\.340"):
            grid.unflat(i)
    with pytest.raises(GridError, match="lat 11"):
        grid.ring_size(11)


# -- neighbours --------------------------------------------------------------------------------


def test_neighbours_on_the_demo_grid():
    grid = grid_for(*DEMO)
    first = GridIndex(lat=0, lon=0)
    assert grid.neighbours(first) == {
        "S": GridIndex(lat=1, lon=0),
        "E": GridIndex(lat=0, lon=1),
        "W": GridIndex(lat=0, lon=5),
    }
    last = GridIndex(lat=10, lon=47)
    assert grid.neighbour(last, "S") is None
    assert grid.neighbour(last, "E") == GridIndex(lat=10, lon=0)
    assert grid.neighbour(last, "N") == GridIndex(lat=9, lon=45)  # 352.5° -> 46 positions
    # 30° on the 12-ring is half-way between 0° and 60° on the 6-ring: the smaller lon wins.
    assert grid.neighbour(GridIndex(lat=1, lon=1), "N") == GridIndex(lat=0, lon=0)
    # 330° is half-way between 300° (lon 5) and 360° ≡ 0° (lon 0): lon 0 is smaller.
    assert grid.neighbour(GridIndex(lat=1, lon=11), "N") == GridIndex(lat=0, lon=0)
    assert grid.neighbour(GridIndex(lat=1, lon=3), "N") == GridIndex(lat=0, lon=1)


def test_pole_neighbours():
    grid = HemisphereGrid(7.5)
    pole = GridIndex(lat=0, lon=0)
    assert grid.neighbours(pole) == {"S": GridIndex(lat=1, lon=0)}
    for lon in range(6):
        assert grid.neighbour(GridIndex(lat=1, lon=lon), "N") == pole


def test_invalid_direction_raises():
    with pytest.raises(ValueError, match="direction must be one of N, S, E, W"):
        grid_for(*DEMO).neighbour(GridIndex(lat=0, lon=0), "up")  # type: ignore[arg-type]


@settings(max_examples=200, deadline=None)
@given(grid_and_index())
def test_neighbour_moves_are_consistent(grid_index):
    grid, index = grid_index
    n = grid.ring_size(index.lat)
    east, west = grid.neighbour(index, "E"), grid.neighbour(index, "W")
    if n == 1:
        assert east is None
        assert west is None
    else:
        assert east == GridIndex(lat=index.lat, lon=(index.lon + 1) % n)
        assert grid.neighbour(east, "W") == index
        assert grid.neighbour(west, "E") == index
        # E is the next position counter-clockwise: φ grows by 360/n (mod 360).
        step = circular_diff_deg(grid.pose(east).phi_deg, grid.pose(index).phi_deg)
        assert float(step) == pytest.approx(360.0 / n)  # n >= 4 off the pole
    north, south = grid.neighbour(index, "N"), grid.neighbour(index, "S")
    assert (north is None) == (index.lat == 0)
    assert (south is None) == (index.lat == grid.ring_count - 1)
    if north is not None:
        assert north.lat == index.lat - 1
        back = grid.neighbour(north, "S")
        assert back is not None
        assert back.lat == index.lat
    if south is not None:
        assert south.lat == index.lat + 1
        back = grid.neighbour(south, "N")
        assert back is not None
        assert back.lat == index.lat
    assert grid.neighbours(index) == {
        d: m for d, m in (("N", north), ("S", south), ("E", east), ("W", west)) if m is not None
    }


@settings(max_examples=200, deadline=None)
@given(grid_and_index(), st.sampled_from(["N", "S"]))
def test_north_south_go_to_the_circularly_nearest_longitude(grid_index, direction):
    grid, index = grid_index
    moved = grid.neighbour(index, direction)
    assume(moved is not None)
    # Brute force in exact rationals: φ_j = j·360/n.
    n, m = grid.ring_size(index.lat), grid.ring_size(moved.lat)
    phi = Fraction(360 * index.lon, n)

    def distance(j: int) -> Fraction:
        d = (Fraction(360 * j, m) - phi) % 360
        return min(d, 360 - d)

    expected = min(range(m), key=lambda j: (distance(j), j))
    assert moved.lon == expected


# -- nearest -----------------------------------------------------------------------------------


@pytest.mark.parametrize("params", GRID_PARAMS)
def test_nearest_of_a_grid_pose_is_itself(params):
    grid = grid_for(*params)
    for index in grid.all_indices():
        assert grid.nearest(grid.pose(index)) == index
    np.testing.assert_array_equal(
        grid.nearest_flat(grid.theta_deg, grid.phi_deg), np.arange(grid.size)
    )


@settings(max_examples=200, deadline=None)
@given(
    grid_and_index(),
    st.floats(-1.0, 1.0),
    st.floats(-1.0, 1.0),
)
def test_nearest_of_a_slightly_perturbed_grid_pose_is_that_pose(grid_index, u, v):
    grid, index = grid_index
    pose = grid.pose(index)
    # Anything closer than half the smallest spacing is nearer to this pose than to any other.
    radius = 0.49 * min_separation_deg(grid)
    theta = pose.theta_deg + u * radius / 2
    sin_theta = max(math.sin(math.radians(pose.theta_deg)), 1e-3)
    phi = pose.phi_deg + v * radius / 2 / sin_theta
    perturbed = Pose(theta_deg=min(max(theta, 0.0), 90.0), phi_deg=phi)
    assume(float(angular_distance_deg(perturbed, pose)) < radius)
    assert grid.nearest(perturbed) == index


@settings(max_examples=150, deadline=None)
@given(grid_params, st.floats(0.0, 180.0), st.floats(-720.0, 720.0))
def test_nearest_is_the_minimum_over_all_grid_poses(params, theta, phi):
    grid = grid_for(*params)
    all_dist = angular_distance_deg((theta, phi), (grid.theta_deg, grid.phi_deg))
    found = int(grid.nearest_flat(theta, phi))
    assert all_dist[found] <= all_dist.min() + 1e-9
    if theta <= 90.0:
        assert grid.nearest(Pose(theta_deg=theta, phi_deg=phi)) == grid.unflat(found)


def test_nearest_is_vectorised():
    grid = grid_for(*DEMO)
    theta = np.array([[7.5, 82.5], [45.0, 10.0]])
    phi = np.array([[0.0, 352.5], [0.0, 180.0]])
    found = grid.nearest_flat(theta, phi)
    assert found.shape == (2, 2)
    for i, j in np.ndindex(2, 2):
        single = grid.nearest(Pose(theta_deg=theta[i, j], phi_deg=phi[i, j]))
        assert found[i, j] == grid.flat(single)


def test_nearest_breaks_ties_by_lowest_index_and_wraps_phi():
    demo = grid_for(*DEMO)
    # The zenith is equally far from all six poses of the 7.5° ring.
    assert demo.nearest(Pose(theta_deg=0.0, phi_deg=200.0)) == GridIndex(lat=0, lon=0)
    assert HemisphereGrid(7.5).nearest(Pose(theta_deg=1.0, phi_deg=200.0)) == GridIndex(
        lat=0, lon=0
    )
    assert demo.nearest(Pose(theta_deg=82.5, phi_deg=359.0)) == GridIndex(lat=10, lon=0)
    assert demo.nearest(Pose(theta_deg=82.5, phi_deg=-8.0)) == GridIndex(lat=10, lon=47)
    assert demo.nearest(Pose(theta_deg=82.5, phi_deg=720.0 + 8.0)) == GridIndex(lat=10, lon=1)


def test_max_grid_size_is_enforced_before_allocating():
    assert MAX_GRID_SIZE >= HemisphereGrid(0.5).size
    with pytest.raises(ValueError, match=str(MAX_GRID_SIZE)):
        HemisphereGrid(1e-9)
