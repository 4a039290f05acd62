"""When is the search done? The test every strategy applies before it moves.

Only the images decide, never the true pose. The current view's detections are matched to the
target's (:func:`~services.optimizer.matching.compare_views`: pairs of alike class and colour,
RMS box-edge difference over the pairs). A match allows unpaired detections in each image up to
a summed *confidence* of ``max_unmatched``: a target detection at confidence 0.3 without a
partner (a doubtful box the search view, rendered at few samples per pixel, does not reproduce)
weighs a third of a sure one. The search is done when

1. the views match *strictly*: RMS within ``tolerance_px``; or
2. the strategy's own estimate puts the target at the current grid pose and the views match
   *loosely*: RMS within the loose tolerance ``T`` below — or, for the map-based strategies,
   the map's prediction at the refined continuous estimate matches the target that closely (a
   target between grid poses).

The strict test alone needs a tolerance below the smallest difference between adjacent grid
views, which can be tiny: near the zenith one 7.5° step in θ moves the demo balls by only
≈ 2 px RMS, less than a real detector's noise. The loose test lets noisy detections and targets
between grid poses finish, but only where the estimate agrees.

The loose tolerance grows with the noise expected of the pairs' box edges. Each edge of pair
``j`` differs between the views by the geometric change ``δ`` plus the two detections' errors,
of standard deviations ``σ_aj``, ``σ_bj`` (:func:`~services.optimizer.observations.edge_sigma`:
pixel quantisation and a fraction of the box size), so the mean squared RMS over the pairs is

.. math:: E[\\mathrm{rms}^2] = δ^2 + N^2, \\qquad
          N^2 = \\frac{1}{P} \\sum_j (σ_{aj}^2 + σ_{bj}^2)

(:attr:`~services.optimizer.matching.ViewComparison.noise_px`), and the test is

.. math:: \\mathrm{rms} \\le T = \\sqrt{(3 \\, t)^2 + (z N)^2}, \\qquad z = 2

(``t`` = ``tolerance_px``, z = :data:`NOISE_SIGMAS`). At the true pose (δ = 0) ``rms²/N²``
is a mean of ``4P`` squared standard normals, whose 99th percentile is below z² = 4 already for
two pairs, so a photo or JPEG target of the true pose passes; a neighbouring pose passes only
with ``δ² < 9 t² + 3 N²`` *and* the estimate at that pose, which the estimate rules out where
neighbouring views differ that little. The strict test is not grown: it has no estimate to rule
out a neighbour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from services.optimizer.matching import ViewComparison
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit

__all__ = ["LOOSE_FACTOR", "NOISE_SIGMAS", "Refined", "done_plan", "matched_text"]

LOOSE_FACTOR: Final = 3.0
"""The loose done test's tolerance before noise, in strict tolerances (module docstring)."""
NOISE_SIGMAS: Final = 2.0
"""z: standard deviations of edge noise the loose done test allows (module docstring)."""


@dataclass(frozen=True)
class Refined:
    """A refined continuous estimate that puts the target nearest the current grid pose.

    ``residual_px`` is its reprojection residual; ``elsewhere`` is set when it was refined at
    another visited pose (the best-scoring one, anchored to its own view), and then
    ``unpaired_target`` is the summed confidence of target detections the map left unpaired
    there."""

    residual_px: float
    elsewhere: bool = False
    unpaired_target: float = 0.0


def matched_text(comparison: ViewComparison) -> str:
    if math.isinf(comparison.rms_px):
        return "no detection pairs with the target"
    text = (
        f"RMS {comparison.rms_px:.2f} px over {len(comparison.pairs)} pairs "
        f"(edge noise {comparison.noise_px:.2f} px), "
        f"{comparison.unmatched_a} current / {comparison.unmatched_b} target unpaired"
    )
    if comparison.unmatched_a or comparison.unmatched_b:
        text += f" (confidence {comparison.unpaired_a:.2f} / {comparison.unpaired_b:.2f})"
    return text


def done_plan(
    problem: SearchProblem,
    current: Visit,
    comparison: ViewComparison,
    est: Estimate | None,
    here: bool,
    refined: Refined | None = None,
    ambiguous: bool = False,
    alternatives: tuple[tuple[int, float], ...] = (),
) -> Plan | None:
    """The done test shared by every strategy (module docstring), or None to keep searching.

    ``refined`` is a map-based strategy's refined continuous estimate nearest the current
    pose: its residual compares the target with the map's prediction at the off-grid pose."""
    tol = problem.tolerance_px
    if comparison.within(tol, problem.max_unmatched):
        if est is None or est.flat != current.flat:
            # The views match: the target is here, whatever a coarser estimate said.
            coverage = len(comparison.pairs) / max(len(problem.target), 1)
            est = Estimate(
                current.flat,
                current.theta_deg,
                current.phi_deg,
                comparison.rms_px,
                coverage * math.exp(-0.5 * (comparison.rms_px / max(tol, 2.0)) ** 2),
            )
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the current view matches the target within {tol:g} px ({matched_text(comparison)})",
        )  # fmt: skip
    if not here:
        return None
    loose = comparison.tolerance(LOOSE_FACTOR * tol, NOISE_SIGMAS)
    if comparison.within(loose, problem.max_unmatched):
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the estimate puts the target at this grid pose and the views agree within "
            f"{loose:.2f} px ({matched_text(comparison)})",
        )  # fmt: skip
    if refined is None or refined.residual_px > loose:
        return None
    # Refined at another view, the prediction pairs the target, not this view (which may look
    # less like the target than that one does).
    if refined.elsewhere:
        paired = refined.unpaired_target <= problem.max_unmatched
    else:
        paired = comparison.paired(problem.max_unmatched)
    refined_px = refined.residual_px
    if paired:
        assert est is not None  # a refined residual comes with its estimate
        return Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the target lies between grid poses, nearest this one: at the refined pose "
            f"θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° the predicted view matches it "
            f"within {refined_px:.2f} px (the grid view differs by {comparison.rms_px:.2f} px)",
        )  # fmt: skip
    return None
