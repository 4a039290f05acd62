"""The paper's pose estimate (§3.3): latitude from the distance-to-centre profile, longitude from
the rotation solve.

The current view, at a known pose, is mapped to world ground positions ``p_m`` with the paper's
mapping (eq. 2–7). The target's pose is unknown, but its camera-relative offsets ``q_j(θ)`` by
eq. 2–6 depend only on the candidate polar angle θ — the camera height ``r cos θ`` — not on φ,
and so do their distances to the scene centre ``|q_j(θ)|``, because the rotation of eq. 7
preserves length. For the true θ these distances match the world distances ``|p_m|`` of the
same objects, so

.. math:: \\hat θ = \\arg\\min_θ \\frac{1}{|P|} \\sum_{(j, m) \\in P}
          \\bigl(|q_j(θ)| − |p_m|\\bigr)^2

over a fine θ grid across the search range ("every candidate camera height"), refined by a
parabola through the best three. The longitude is then the closed-form rotation solve
(:mod:`.longitude`) between ``q_j(θ̂)`` and ``p_m``.

The pairs ``P`` come from appearance alone (class and colour) when that is unique; when several
objects look alike the assignment is redone at every θ by a gated Hungarian on
``((|q_j| − |p_m|)/σ)² + colour cost`` — geometry then picks the pairs, and the estimate is
flagged ambiguous when a second assignment fits almost as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from services.common.caches import SharedLru, array_nbytes
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import PaperCalibration
from services.optimizer.geometry import FloatArray
from services.optimizer.longitude import solve_rotation
from services.optimizer.mapping import map_paper, paper_offsets
from services.optimizer.matching import COLOUR_GATE, Assignment, assign
from services.optimizer.observations import ALIKE_COST, Observation, appearance_cost

__all__ = ["LayoutEstimate", "estimate_layout"]

_PROFILE_SIGMA: Final = 0.02  # σ of a distance-to-centre mismatch, per unit radius
_MIN_COHERENCE: Final = 0.9


@dataclass(frozen=True)
class LayoutEstimate:
    """The target pose from matched layouts.

    Attributes
    ----------
    theta_deg, phi_deg : float
        Continuous estimate; NaN when it failed.
    residual : float
        RMS ground residual of the rotation fit, scene units.
    coherence : float
        Agreement of the pairs on one rotation (:class:`~.longitude.RotationFit`).
    matched : int
        Pairs used.
    ambiguous : bool
        Whether the layout does not pin the pose down.
    reason : str
        Why it failed or is ambiguous (empty otherwise).
    """

    theta_deg: float
    phi_deg: float
    residual: float
    coherence: float
    matched: int
    ambiguous: bool
    reason: str

    @property
    def ok(self) -> bool:
        return math.isfinite(self.theta_deg) and math.isfinite(self.phi_deg)


def _failed(reason: str, matched: int = 0) -> LayoutEstimate:
    return LayoutEstimate(math.nan, math.nan, math.nan, 0.0, matched, True, reason)


def _unique_pairs(looks: FloatArray) -> Assignment | None:
    """The appearance-only assignment when every pair is the only alike candidate both ways."""
    alike = looks < ALIKE_COST
    pairs = assign(np.where(looks < COLOUR_GATE, looks, np.inf), COLOUR_GATE)
    if not len(pairs):
        return None
    rows_unique = alike[pairs.rows].sum(axis=1) <= 1
    cols_unique = alike[:, pairs.cols].sum(axis=0) <= 1
    return pairs if bool(np.all(rows_unique & cols_unique)) else None


_CANDIDATES_BYTES: Final = 8 * 2**20
"""Memory for targets' distance profiles: ~8 kB for five detections over ~200 candidate θ."""
_MAPPED_BYTES: Final = 4 * 2**20
"""Memory for current views' paper mappings: ~1 kB each."""

_candidate_profiles: Final = SharedLru[tuple[FloatArray, FloatArray]](
    _CANDIDATES_BYTES, weigh=array_nbytes
)
_mapped_views: Final = SharedLru[tuple[Observation, FloatArray]](_MAPPED_BYTES, weigh=array_nbytes)


def _candidates(
    target: Observation, camera: CameraSpec, grid: HemisphereGrid, calibration: PaperCalibration
) -> tuple[FloatArray, FloatArray]:
    """Candidate θ ``(T,)`` and the target's distances to the centre ``|q_j(θ)|`` ``(T, n)``;
    cached by the target's content (a search's requests resend it as new objects)."""

    def profile() -> tuple[FloatArray, FloatArray]:
        step = grid.angle_step_deg
        lo = max(0.0, float(grid.theta_deg[0]) - step / 2.0)
        hi = min(90.0, float(grid.theta_deg[-1]) + step / 2.0)
        count = max(3, int(math.ceil((hi - lo) / min(0.5, step / 8.0))) + 1)
        thetas = np.linspace(lo, hi, count)
        offsets = paper_offsets(target.boxes, camera, thetas, calibration)
        return thetas, np.linalg.norm(offsets, axis=-1)

    return _candidate_profiles.get((target.digest, camera, grid, calibration), profile)


def _mapped(
    current: Observation,
    theta_deg: float,
    phi_deg: float,
    camera: CameraSpec,
    calibration: PaperCalibration,
) -> tuple[Observation, FloatArray]:
    """The current view's usable detections and their paper-mapped world positions; cached by
    content (a view sent again, as every search's start view is)."""

    def mapped() -> tuple[Observation, FloatArray]:
        world = map_paper(current.boxes, camera, theta_deg, phi_deg, calibration)
        return current.subset(world.reliable), world.position[world.reliable]

    key = (current.digest, theta_deg, phi_deg, camera, calibration)
    return _mapped_views.get(key, mapped)


def estimate_layout(
    target: Observation,
    current: Observation,
    theta_deg: float,
    phi_deg: float,
    camera: CameraSpec,
    grid: HemisphereGrid,
    calibration: PaperCalibration,
) -> LayoutEstimate:
    """Estimate the target's pose from the current view at (θ, φ) (module docstring)."""
    ref, positions = _mapped(current, theta_deg, phi_deg, camera, calibration)
    if len(ref) == 0:
        return _failed("no object of the current view could be mapped")
    thetas, radial = _candidates(target, camera, grid, calibration)
    world_radial = np.linalg.norm(positions, axis=-1)  # (M,)
    mismatch = max(target.mismatch_cost, ref.mismatch_cost)
    looks = appearance_cost(target.labels, target.colors, ref.labels, ref.colors, mismatch)
    sigma = _PROFILE_SIGMA * camera.radius
    fixed = _unique_pairs(looks)
    ambiguous = fixed is None
    if fixed is not None:
        rows, cols = fixed.rows, fixed.cols
        mismatch = (radial[:, rows] - world_radial[cols]) ** 2
        with np.errstate(invalid="ignore"):
            profile = np.where(np.isfinite(mismatch).all(axis=1), mismatch.mean(axis=1), np.inf)
        pairs_at = [fixed] * len(thetas)
    else:
        profile = np.full(len(thetas), np.inf)
        pairs_at = []
        for t in range(len(thetas)):
            geometric = ((radial[t][:, np.newaxis] - world_radial[np.newaxis, :]) / sigma) ** 2
            cost = np.where(looks < COLOUR_GATE, geometric + looks, np.inf)
            pairs = assign(cost, 9.0 + COLOUR_GATE)
            pairs_at.append(pairs)
            if len(pairs) >= 1:
                d = radial[t, pairs.rows] - world_radial[pairs.cols]
                # Unpaired detections cost as much as the gate, so θ cannot win by pairing less.
                missing = len(target) - len(pairs)
                profile[t] = (np.sum(d**2) + missing * (3.0 * sigma) ** 2) / len(target)
    if not np.isfinite(profile).any():
        return _failed("no target detection matches an object of the current view")
    best = int(np.argmin(profile))
    theta_hat = float(thetas[best])
    if 0 < best < len(thetas) - 1 and np.isfinite(profile[best - 1 : best + 2]).all():
        y0, y1, y2 = profile[best - 1 : best + 2]
        curvature = y0 - 2.0 * y1 + y2
        if curvature > 0:
            theta_hat += 0.5 * (y0 - y2) / curvature * float(thetas[1] - thetas[0])
    pairs = pairs_at[best]
    q = paper_offsets(target.boxes[pairs.rows], camera, [theta_hat], calibration)[0]
    fit = solve_rotation(q, positions[pairs.cols])
    reasons = []
    if len(pairs) < 2:
        ambiguous = True
        reasons.append(f"only {len(pairs)} object matched between the views")
    if fit.coherence < _MIN_COHERENCE:
        ambiguous = True
        reasons.append(f"the matched objects disagree on the longitude (κ = {fit.coherence:.2f})")
    if fixed is None:
        reasons.append("several objects look alike; pairs chosen by geometry")
    if not fit.determined:
        return _failed("; ".join(reasons) or "the longitude is undetermined", len(pairs))
    return LayoutEstimate(
        theta_deg=float(np.clip(theta_hat, 0.0, 90.0)),
        phi_deg=fit.phi_deg,
        residual=fit.rms,
        coherence=fit.coherence,
        matched=len(pairs),
        ambiguous=ambiguous,
        reason="; ".join(reasons),
    )
