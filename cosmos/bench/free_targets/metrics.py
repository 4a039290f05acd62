"""How far an estimated camera is from the truth, and the shares a set of targets reaches.

* position error: ``|c_est - c_true| / r``, r the scene's hemisphere radius;
* rotation error: the angle of ``R_estᵀ R_true`` in degrees (either convention, camera-to-world
  or world-to-camera, gives the same angle);
* fov error: ``|fov_est - fov_true| / fov_true`` in %.

A target without an answer counts as infinitely far: it is within no threshold, and it moves the
median and p95 up as a miss should.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.spatial.transform import Rotation

from cosmos.bench.free_targets.estimate import Estimate

__all__ = [
    "THRESHOLDS",
    "ErrorSummary",
    "PoseError",
    "pose_error",
    "rotation_angle_deg",
    "summarize",
]

THRESHOLDS: Final = ((0.02, 1.0), (0.05, 2.0), (0.10, 5.0))
"""(position error as a fraction of r, rotation error in degrees) pairs the issue's goals use."""


@dataclass(frozen=True)
class PoseError:
    """One target's errors: position in radii, rotation in degrees, fov in %."""

    position: float
    rotation_deg: float
    fov_pct: float

    def within(self, position: float, rotation_deg: float) -> bool:
        return self.position <= position and self.rotation_deg <= rotation_deg


MISSED: Final = PoseError(math.inf, math.inf, math.inf)


def rotation_angle_deg(estimated: np.ndarray, true: np.ndarray) -> float:
    """The angle in degrees of the rotation ``estimatedᵀ true`` (0 for the same rotation)."""
    relative = np.asarray(estimated, dtype=np.float64).T @ np.asarray(true, dtype=np.float64)
    return float(np.degrees(Rotation.from_matrix(relative).magnitude()))


def pose_error(estimate: Estimate | None, truth: Estimate, radius: float) -> PoseError:
    """The errors of ``estimate`` against ``truth`` (:data:`MISSED` without an estimate)."""
    if estimate is None:
        return MISSED
    return PoseError(
        position=float(np.linalg.norm(estimate.position - truth.position)) / radius,
        rotation_deg=rotation_angle_deg(estimate.rotation, truth.rotation),
        fov_pct=abs(estimate.fov_deg - truth.fov_deg) / truth.fov_deg * 100.0,
    )


@dataclass(frozen=True)
class ErrorSummary:
    """The figures of a set of targets: how many, how many without an answer, the share within
    each of :data:`THRESHOLDS`, and median and p95 of each error."""

    count: int
    missed: int
    within: tuple[float, ...]
    position_median: float
    position_p95: float
    rotation_median_deg: float
    rotation_p95_deg: float
    fov_median_pct: float
    fov_p95_pct: float


def _quantile(values: Sequence[float], q: float) -> float:
    """The ``q`` quantile, with infinities (misses) taken as the largest values."""
    if not values:
        return math.nan
    ordered = np.sort(np.asarray(values, dtype=np.float64))
    rank = q * (len(ordered) - 1)
    lo, hi = math.floor(rank), math.ceil(rank)
    if lo == hi:
        return float(ordered[lo])
    if math.isinf(ordered[hi]):
        return math.inf
    return float(ordered[lo] + (ordered[hi] - ordered[lo]) * (rank - lo))


def summarize(errors: Sequence[PoseError]) -> ErrorSummary:
    """The figures of ``errors`` (:class:`ErrorSummary`)."""
    n = len(errors)
    shares = tuple(
        sum(e.within(p, r) for e in errors) / n if n else math.nan for p, r in THRESHOLDS
    )
    positions = [e.position for e in errors]
    rotations = [e.rotation_deg for e in errors]
    fovs = [e.fov_pct for e in errors]
    return ErrorSummary(
        count=n,
        missed=sum(math.isinf(e.position) for e in errors),
        within=shares,
        position_median=_quantile(positions, 0.5),
        position_p95=_quantile(positions, 0.95),
        rotation_median_deg=_quantile(rotations, 0.5),
        rotation_p95_deg=_quantile(rotations, 0.95),
        fov_median_pct=_quantile(fovs, 0.5),
        fov_p95_pct=_quantile(fovs, 0.95),
    )
