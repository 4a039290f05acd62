"""The discretised camera hemisphere (paper eq. 1): grid rings, indices, neighbours, nearest pose.

Poses, their angles (degrees) and camera positions follow :mod:`.sphere`'s conventions.

The grid (eq. 1) has rings at θ_k = k·Δ for the integers k with θ_min ≤ θ_k ≤ θ_max (Δ the
angle step). Ring k holds

.. math:: n_k = \\max\\bigl(1,\\ \\operatorname{round}(360 \\sin θ_k / Δ)\\bigr)

positions at φ_j = j·360/n_k, j = 0 … n_k − 1, so neighbouring positions are about Δ apart
along the ring as well as across rings. ``round`` is round-half-up, ⌊x + ½⌋, not Python's
round-half-even, so a tie never depends on the parity of its neighbours; a slack of 1e-9 lets a
tie that floating-point error pushed just below ½ still round up. At Δ = 7.5° the equator
(θ = 90°) holds 48 positions and the pole one.

Grid poses are addressed by :class:`~services.common.geometry.pose.GridIndex` ``(lat, lon)``:
``lat`` counts rings from the lowest θ in range (0 = first ring), ``lon`` counts positions on
the ring from φ = 0 counter-clockwise. The flat order used by the pose arrays is lat-major.
"""

from __future__ import annotations

import functools
import math
from typing import Annotated, Final, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator

from services.common.base import FrozenModel, Integer, NonNegInt, Number, ThetaDeg
from services.common.geometry.pose import GridIndex, Pose
from services.common.geometry.sphere import pose_to_cartesian

__all__ = [
    "MAX_GRID_SIZE",
    "Direction",
    "GridError",
    "GridRing",
    "GridSpec",
    "HemisphereGrid",
    "grid_for",
]

Direction = Literal["N", "S", "E", "W"]
"""Grid neighbour directions: N toward the zenith (lat − 1), S away from it (lat + 1),
E increasing φ (lon + 1), W decreasing φ (lon − 1)."""

MAX_GRID_SIZE: Final = 5_000_000
"""Largest number of grid poses a :class:`HemisphereGrid` accepts (Δ ≈ 0.06° at full range);
the grid keeps one unit vector per pose, so this bounds its memory to about 120 MB."""

_DIRECTIONS: Final = get_args(Direction)
_RING_TOL_DEG: Final = 1e-9  # a ring θ_k = k·Δ within this of [θ_min, θ_max] is kept
_ROUND_SLACK: Final = 1e-9
_INDEX_TOL_DEG: Final = 1e-6


class GridError(ValueError):
    """A grid index or pose that is not on the grid (bad ``lat``/``lon``, flat index, or pose)."""


def _round_half_up(x: NDArray[np.float64]) -> NDArray[np.int64]:
    return np.floor(x + 0.5 + _ROUND_SLACK).astype(np.int64)


def _readonly(array: NDArray[np.float64]) -> NDArray[np.float64]:
    array.setflags(write=False)
    return array


class HemisphereGrid:
    """The discretised camera hemisphere of eq. 1 (see the module docstring for conventions).

    Immutable, hashable and compared by its parameters; build it through :func:`grid_for` to
    share one instance per parameter set.

    Parameters
    ----------
    angle_step_deg : float
        Angle step Δ in (0, 90] degrees, both between rings and along a ring.
    min_theta_deg, max_theta_deg : float
        Range of ring polar angles, 0 ≤ θ_min ≤ θ_max ≤ 90 degrees; a ring θ_k = k·Δ is kept
        when it lies in the range within 1e-9°.

    Raises
    ------
    ValueError
        If a parameter is not finite or out of range, no ring lies in the range, or the grid
        would hold more than :data:`MAX_GRID_SIZE` poses.
    """

    def __init__(
        self, angle_step_deg: float, min_theta_deg: float = 0.0, max_theta_deg: float = 90.0
    ) -> None:
        step, lo, hi = float(angle_step_deg), float(min_theta_deg), float(max_theta_deg)
        # Written so that NaN, which fails every comparison, is rejected too.
        if not 0.0 < step <= 90.0:
            raise ValueError(f"angle_step_deg must be in (0, 90] degrees, got {angle_step_deg!r}")
        if not 0.0 <= lo <= hi <= 90.0:
            raise ValueError(
                "need 0 <= min_theta_deg <= max_theta_deg <= 90 degrees, "
                f"got min_theta_deg={min_theta_deg!r}, max_theta_deg={max_theta_deg!r}"
            )
        k_first = max(0, math.ceil((lo - _RING_TOL_DEG) / step))
        k_last = math.floor((hi + _RING_TOL_DEG) / step)
        if k_last < k_first:
            raise ValueError(
                f"no ring θ = k·{step:g}° lies in [{lo:g}°, {hi:g}°]; "
                "widen the θ range or shrink angle_step_deg"
            )
        if k_last - k_first + 1 > MAX_GRID_SIZE:
            raise ValueError(f"angle_step_deg={step:g} gives more than {MAX_GRID_SIZE} grid poses")

        ring_theta = np.minimum(np.arange(k_first, k_last + 1) * step, 90.0)
        counts = np.maximum(1, _round_half_up(360.0 * np.sin(np.radians(ring_theta)) / step))
        size = int(counts.sum())
        if size > MAX_GRID_SIZE:
            raise ValueError(
                f"angle_step_deg={step:g} gives {size} grid poses, more than {MAX_GRID_SIZE}"
            )

        self._key = (step, lo, hi)
        self._ring_theta = _readonly(ring_theta)
        self._counts: tuple[int, ...] = tuple(int(n) for n in counts)
        self._offsets = np.concatenate(([0], np.cumsum(counts)))
        lat_of = np.repeat(np.arange(len(counts)), counts)
        lon_of = np.arange(size) - self._offsets[lat_of]
        self._theta = _readonly(ring_theta[lat_of])
        self._phi = _readonly(lon_of * 360.0 / counts[lat_of])
        self._unit = _readonly(pose_to_cartesian(self._theta, self._phi))
        self._rings = tuple(
            GridRing(lat=lat, theta_deg=float(theta), count=n)
            for lat, (theta, n) in enumerate(zip(ring_theta, self._counts, strict=True))
        )

    def __repr__(self) -> str:
        step, lo, hi = self._key
        return (
            f"HemisphereGrid(angle_step_deg={step!r}, min_theta_deg={lo!r}, max_theta_deg={hi!r})"
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, HemisphereGrid):
            return NotImplemented
        return self._key == other._key

    def __hash__(self) -> int:
        return hash(self._key)

    # -- shape -------------------------------------------------------------------------------

    @property
    def angle_step_deg(self) -> float:
        """Angle step Δ in degrees."""
        return self._key[0]

    @property
    def rings(self) -> tuple[GridRing, ...]:
        """The rings in order of increasing θ (``lat`` 0 first)."""
        return self._rings

    @property
    def ring_count(self) -> int:
        """Number of rings."""
        return len(self._counts)

    @property
    def size(self) -> int:
        """Total number of grid poses, Σ n_k."""
        return int(self._offsets[-1])

    @property
    def theta_deg(self) -> NDArray[np.float64]:
        """θ of every grid pose in flat (lat-major) order, degrees; read-only."""
        return self._theta

    @property
    def phi_deg(self) -> NDArray[np.float64]:
        """φ of every grid pose in flat (lat-major) order, degrees in [0, 360); read-only."""
        return self._phi

    def ring_size(self, lat: int) -> int:
        """Number of positions n_k on ring ``lat``; raises :class:`GridError` if there is none."""
        self._validate_lat(lat)
        return self._counts[lat]

    def spec(self) -> GridSpec:
        """The grid's message form (its parameters; rings and size follow from them)."""
        step, lo, hi = self._key
        return GridSpec(angle_step_deg=step, min_theta_deg=lo, max_theta_deg=hi)

    def _validate_lat(self, lat: int) -> None:
        if not 0 <= lat < self.ring_count:
            raise GridError(f"lat {lat} is out of range: valid rings are 0..{self.ring_count - 1}")

    def contains(self, index: GridIndex) -> bool:
        """Whether ``index`` addresses a pose of this grid."""
        return 0 <= index.lat < self.ring_count and 0 <= index.lon < self._counts[index.lat]

    def validate(self, index: GridIndex) -> None:
        """Raise :class:`GridError` naming ``lat`` or ``lon`` and its valid range if ``index`` is
        not on the grid."""
        self._validate_lat(index.lat)
        n = self._counts[index.lat]
        if not 0 <= index.lon < n:
            theta = self._rings[index.lat].theta_deg
            raise GridError(
                f"lon {index.lon} is out of range for ring lat={index.lat} "
                f"(θ = {theta:g}°): valid positions are 0..{n - 1}"
            )

    def all_indices(self) -> tuple[GridIndex, ...]:
        """Every grid index in flat (lat-major) order."""
        return tuple(
            GridIndex(lat=lat, lon=lon) for lat, n in enumerate(self._counts) for lon in range(n)
        )

    def flat(self, index: GridIndex) -> int:
        """Position of ``index`` in the flat (lat-major) order: offset of ring ``lat`` + ``lon``."""
        self.validate(index)
        return int(self._offsets[index.lat]) + index.lon

    def unflat(self, i: int) -> GridIndex:
        """The grid index at flat position ``i``; the inverse of :meth:`flat`."""
        if not 0 <= i < self.size:
            raise GridError(f"flat index {i} is out of range: valid are 0..{self.size - 1}")
        lat = int(np.searchsorted(self._offsets, i, side="right")) - 1
        return GridIndex(lat=lat, lon=i - int(self._offsets[lat]))

    # -- poses -------------------------------------------------------------------------------

    def pose(self, index: GridIndex) -> Pose:
        """The pose (θ_k, φ_j = j·360/n_k) at ``index``."""
        i = self.flat(index)
        return Pose(theta_deg=float(self._theta[i]), phi_deg=float(self._phi[i]))

    def index_of(self, pose: Pose, *, tol_deg: float = _INDEX_TOL_DEG) -> GridIndex:
        """The index of a grid pose given by its angles.

        θ must be within ``tol_deg`` of a ring and φ (circularly) within ``tol_deg`` of a
        position on it; on the pole ring φ is ignored (every φ is the same view).

        Raises
        ------
        GridError
            If ``pose`` is not a grid pose.
        """
        ring_theta = self._ring_theta
        lat = int(np.argmin(np.abs(ring_theta - pose.theta_deg)))
        if abs(ring_theta[lat] - pose.theta_deg) > tol_deg:
            raise GridError(
                f"θ = {pose.theta_deg:g}° is not a ring of this grid "
                f"(rings at k·{self.angle_step_deg:g}° for θ in "
                f"[{ring_theta[0]:g}°, {ring_theta[-1]:g}°])"
            )
        n = self._counts[lat]
        if n == 1:
            return GridIndex(lat=lat, lon=0)
        lon = math.floor(pose.phi_deg * n / 360.0 + 0.5) % n
        off = (pose.phi_deg - lon * 360.0 / n + 180.0) % 360.0 - 180.0
        if abs(off) > tol_deg:
            raise GridError(
                f"φ = {pose.phi_deg:g}° is not a position of ring lat={lat} "
                f"(θ = {ring_theta[lat]:g}°, φ = j·360°/{n})"
            )
        return GridIndex(lat=lat, lon=lon)

    def nearest_flat(self, theta_deg: ArrayLike, phi_deg: ArrayLike) -> NDArray[np.intp]:
        """Flat indices of the grid poses nearest to the given poses by view direction.

        Minimising the great-circle angle α_i to grid direction **u**_i is maximising
        **u**_i · **q** for the query direction **q**, so this is one matrix product over all
        grid poses. Exact ties go to the lowest flat index.

        Parameters
        ----------
        theta_deg, phi_deg : array_like
            Broadcastable query angles in degrees (any θ, including below the horizon).

        Returns
        -------
        ndarray of intp
            Flat indices, shaped like the broadcast queries.
        """
        queries = pose_to_cartesian(theta_deg, phi_deg)
        dots = queries.reshape(-1, 3) @ self._unit.T
        best: NDArray[np.intp] = np.argmax(dots, axis=1).reshape(queries.shape[:-1])
        return best

    def nearest(self, pose: Pose) -> GridIndex:
        """The grid pose nearest to ``pose`` by great-circle angle between view directions.

        Exact ties go to the lowest flat index (lat-major), e.g. the pole seen from a grid
        without one maps to ``GridIndex(lat=0, lon=0)``.
        """
        return self.unflat(int(self.nearest_flat(pose.theta_deg, pose.phi_deg)))

    # -- neighbours --------------------------------------------------------------------------

    def neighbour(self, index: GridIndex, direction: Direction) -> GridIndex | None:
        """The neighbouring grid pose of ``index`` in ``direction``, or None at an edge.

        N and S move to ring lat − 1 (smaller θ) and lat + 1 (larger θ), to the position whose
        φ is circularly nearest to φ_j = j·360/n: with m positions on the new ring that is
        j' = round(j·m/n) mod m, computed in integers so that a tie (j·m/n exactly half-way)
        reliably goes to the smaller ``lon``. E and W step ``lon`` by ±1 modulo n; a ring with one
        position (the pole) has no E or W neighbour.

        Raises
        ------
        GridError
            If ``index`` is not on the grid.
        ValueError
            If ``direction`` is not one of ``"N"``, ``"S"``, ``"E"``, ``"W"``.
        """
        if direction not in _DIRECTIONS:
            raise ValueError(
                f"direction must be one of {', '.join(_DIRECTIONS)}, got {direction!r}"
            )
        self.validate(index)
        lat, lon = index.lat, index.lon
        n = self._counts[lat]
        if direction in ("E", "W"):
            if n == 1:
                return None
            step = 1 if direction == "E" else -1
            return GridIndex(lat=lat, lon=(lon + step) % n)
        new_lat = lat - 1 if direction == "N" else lat + 1
        if not 0 <= new_lat < self.ring_count:
            return None
        m = self._counts[new_lat]
        below, rem = divmod(lon * m, n)  # j·m/n = below + rem/n
        above = (below + 1) % m
        below %= m
        if 2 * rem < n:
            new_lon = below
        elif 2 * rem > n:
            new_lon = above
        else:
            new_lon = min(below, above)
        return GridIndex(lat=new_lat, lon=new_lon)

    def neighbours(self, index: GridIndex) -> dict[Direction, GridIndex]:
        """The existing neighbours of ``index``, keyed by direction (N, S, E, W order)."""
        found: dict[Direction, GridIndex] = {}
        for direction in _DIRECTIONS:
            neighbour = self.neighbour(index, direction)
            if neighbour is not None:
                found[direction] = neighbour
        return found


class GridRing(FrozenModel):
    """One ring of the hemisphere grid."""

    lat: NonNegInt
    theta_deg: ThetaDeg
    count: Annotated[Integer, Field(ge=1)]


class GridSpec(FrozenModel):
    """The hemisphere grid of camera poses (eq. 1): rings every ``angle_step_deg`` in the θ range.

    One type from the scene file's ``search`` section through the renderer's scene detail to the
    optimizer's request; :meth:`grid` gives its rings, indices and neighbours.
    """

    angle_step_deg: Annotated[Number, Field(gt=0.0, le=90.0)] = 7.5
    min_theta_deg: ThetaDeg = 0.0
    max_theta_deg: ThetaDeg = 90.0

    @model_validator(mode="after")
    def _has_a_ring(self) -> GridSpec:
        if self.min_theta_deg > self.max_theta_deg:
            raise ValueError("min_theta_deg must not exceed max_theta_deg")
        self.grid()  # raises GridError (a ValueError) when no ring lies in range or too many poses
        return self

    def grid(self) -> HemisphereGrid:
        """The shared :class:`HemisphereGrid` of these parameters."""
        return grid_for(self.angle_step_deg, self.min_theta_deg, self.max_theta_deg)


@functools.lru_cache(maxsize=32)
def grid_for(
    angle_step_deg: float, min_theta_deg: float = 0.0, max_theta_deg: float = 90.0
) -> HemisphereGrid:
    """The shared :class:`HemisphereGrid` for these parameters (built once, then cached)."""
    return HemisphereGrid(angle_step_deg, min_theta_deg, max_theta_deg)
