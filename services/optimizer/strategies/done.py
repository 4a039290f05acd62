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

Both tests are tried on the full match and, failing that, as if one object of the site changed
since the scene file (:func:`one_object_changed`): with the worst pair left unpaired
(:func:`~services.optimizer.matching.without_worst_pair`: at least three pairs stay and the two
detections' confidence fits the ``max_unmatched`` allowance), or with one object's unpaired
detections left out of the allowance
(:func:`~services.optimizer.matching.without_changed_object`: moved far, gone, or come; at least
three pairs). One object moved, removed or added, or a doubtful box of the general detector put
on another part of an object, must not hold up a view whose other objects agree to a pixel.

An answer done on the strength of the estimate (2.) whose estimate lies almost on the boundary
between its grid pose and another (:data:`EDGE_MARGIN_STEPS`) is ambiguous: which of the two is
nearest the target is then within the estimate's own error (a target between grid poses), and
a confirmed answer must not hang on it. So is one whose views share fewer than
:data:`MIN_ESTIMATE_PAIRS` pairs: two boxes leave that error too large to tell neighbours apart.
So is one over just that many pairs whose views differ by more than their edge noise explains
(``rms > z N``, let through by the ``3 t`` of the tolerance): an object moved since the scene
file, or boxed wrongly, then bends an estimate that rests on three boxes, and the neighbour it
leans to is rendered to settle it (see :func:`_ambiguous_if_undecided`).
So is one whose own standard deviation ``σ`` (the refinement's Gauss–Newton covariance, see
:class:`~services.optimizer.reprojection.Refinement`) reaches that boundary
(:data:`SIGMA_MARGIN`): near the zenith a step of θ moves the objects little, and the same box
noise leaves θ open by degrees.
So is one whose estimate cannot rule out another grid pose (:class:`Rival`): an estimate that
is only its grid pose's score, not refined between grid poses (no view anchors the map's
prediction there), has no say on whether a neighbour lies nearer the target; nor has one whose
robust refinement lies nearer another grid pose, this one kept only for its smaller RMS (an
outlier pair, such as one object boxed twice, pulls the two apart). A neighbour's view passes
the loose test too where neighbouring views differ by less than ``T``.

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

import functools
import math
from dataclasses import dataclass, replace
from typing import Final

import numpy as np

from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer.geometry import FloatArray
from services.optimizer.matching import (
    ViewComparison,
    without_changed_object,
    without_worst_pair,
)
from services.optimizer.observations import Observation
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit

__all__ = [
    "LOOSE_FACTOR",
    "NOISE_SIGMAS",
    "Refined",
    "Rival",
    "done_plan",
    "loose_tolerance",
    "matched_text",
    "one_object_changed",
]

LOOSE_FACTOR: Final = 3.0
"""The loose done test's tolerance before noise, in strict tolerances (module docstring)."""
NOISE_SIGMAS: Final = 2.0
"""z: standard deviations of edge noise the loose done test allows (module docstring)."""
EDGE_MARGIN_STEPS: Final = 0.2
"""An estimate nearer its grid pose than another by less than this many grid steps of angle
makes a done answer ambiguous (:func:`_ambiguous_if_undecided`)."""
SIGMA_MARGIN: Final = 1.0
"""An estimate whose boundary with another grid pose lies within this many of its own standard
deviations makes a done answer ambiguous (:func:`_ambiguous_if_undecided`). Measured with the
general model on generated scenes (``cosmos bench --random-scenes 5 --n 5 --onboard none
--starts given,predicted --seed S``, 300 searches each, one run each way): at 1, confirmed
right 179 → 177 and 239 → 231 on seeds 7 and 8, and seed 8's confirmed wrong answer (θ 8.5°,
refined to 15.7°, σ 3.1°) ambiguous; at 2, 179 → 157, 239 → 220 and 258 → 249 (seed 9): the σ
of the residuals overstates the error of most estimates (on-grid JPEG targets 0.2° off at a σ
of 1.9°)."""
MIN_ESTIMATE_PAIRS: Final = 3
"""A done answer resting on the estimate, with fewer pairs than this between the views, is
ambiguous (:func:`_ambiguous_if_undecided`). Measured with the general model on generated
scenes (``cosmos bench --random-scenes 5 --n 5 --onboard none --seed 7``, 300 searches): 4 of
its 5 confirmed wrong answers were done so over 2 pairs (two look-alike objects), their
estimates 3.4–5.9° off on a 5° grid. With this rule: confirmed wrong 5 → 1, confirmed right
186 → 179, found 282 either way; on the built-in scenes (``cosmos bench --scenes demo,garden
--n 5 --strategies reprojection --seed 3``, 80 searches) nothing changed."""


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


@dataclass(frozen=True)
class Rival:
    """A grid pose (``flat``) that the estimate cannot rule out, ``score`` being the map's score
    there (lower is better), and ``why`` it cannot."""

    flat: int
    score: float
    why: str
    settled_by_views: bool = True
    """Whether the rival's view, ruled out, confirms the answer (:mod:`.settle`,
    :attr:`~services.optimizer.problem.Plan.vindicated`): not when the estimate itself prefers
    the rival (a robust fit nearer it), since a worse view of the rival then does not vindicate
    this pose; the rival is still rendered, and ends the search when its own view passes. Near
    the zenith a view's box RMS follows φ (the image's turn about its centre) more than θ, and
    a pose of the target's φ two rings off matched better than the rival a ring off: with the
    general model on generated scenes (``cosmos bench --random-scenes 5 --n 5 --onboard none
    --starts given,predicted --seed 10``) a target at θ 11.4° was confirmed at θ 20° that way,
    with a given and with a predicted start."""


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
    if comparison.changed:
        text += f", besides {comparison.changed}"
    return text


def loose_tolerance(comparison: ViewComparison, tolerance_px: float) -> float:
    """The loose done test's ``T = √((3 t)² + (z N)²)`` for ``comparison`` (module docstring)."""
    return comparison.tolerance(LOOSE_FACTOR * tolerance_px, NOISE_SIGMAS)


def done_plan(
    problem: SearchProblem,
    current: Visit,
    comparison: ViewComparison,
    est: Estimate | None,
    here: bool,
    refined: Refined | None = None,
    ambiguous: bool = False,
    alternatives: tuple[tuple[int, float], ...] = (),
    rival: Rival | None = None,
    checks: tuple[int, ...] | None = None,
) -> Plan | None:
    """The done test shared by every strategy (module docstring), or None to keep searching.

    ``refined`` is a map-based strategy's refined continuous estimate nearest the current
    pose: its residual compares the target with the map's prediction at the off-grid pose.
    ``rival`` is a grid pose the estimate cannot rule out: an answer done on the estimate is
    then ambiguous. ``checks`` are the grid poses whose views settle an ``ambiguous`` answer
    (:attr:`~services.optimizer.problem.Plan.checks`)."""
    tol = problem.tolerance_px
    matches = (comparison, *one_object_changed(problem, current.observation, comparison))
    strict = next((c for c in matches if _within(c, tol, problem)), None)
    if strict is not None:
        comparison = strict
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
            checks,
        )  # fmt: skip
    if not here:
        return None
    for agreeing in matches:
        loose = loose_tolerance(agreeing, tol)
        if _within(agreeing, loose, problem):
            plan = Plan(
                True, current.flat, "stay", est, ambiguous, alternatives,
                f"the estimate puts the target at this grid pose and the views agree within "
                f"{loose:.2f} px ({matched_text(agreeing)})", checks,
            )  # fmt: skip
            beyond = agreeing.rms_px > NOISE_SIGMAS * agreeing.noise_px
            return _ambiguous_if_undecided(problem, plan, len(agreeing.pairs), rival, beyond)
    loose = loose_tolerance(comparison, tol)
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
        return _ambiguous_if_undecided(problem, Plan(
            True, current.flat, "stay", est, ambiguous, alternatives,
            f"the target lies between grid poses, nearest this one: at the refined pose "
            f"θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° the predicted view matches it "
            f"within {refined_px:.2f} px (the grid view differs by {comparison.rms_px:.2f} px)",
            checks,
        ), len(comparison.pairs), rival)  # fmt: skip
    return None


def one_object_changed(
    problem: SearchProblem, observation: Observation, comparison: ViewComparison
) -> tuple[ViewComparison, ...]:
    """The view's ``comparison`` with the target as it stands if one object of the site changed
    since the scene file: without its worst pair, or without one object's unpaired detections
    (:func:`~services.optimizer.matching.without_worst_pair`,
    :func:`~services.optimizer.matching.without_changed_object`), those that exist."""
    target = problem.target
    trimmed = without_worst_pair(observation, target, comparison, problem.max_unmatched)
    changed = without_changed_object(observation, target, comparison)
    return tuple(c for c in (trimmed, changed) if c is not None)


def _within(comparison: ViewComparison, rms_px: float, problem: SearchProblem) -> bool:
    return comparison.within(rms_px, problem.max_unmatched)


@functools.lru_cache(maxsize=16)
def _units(grid: HemisphereGrid) -> FloatArray:
    """Unit view directions of every grid pose (flat order)."""
    return pose_to_cartesian(grid.theta_deg, grid.phi_deg).reshape(-1, 3)


def _ambiguous_if_undecided(
    problem: SearchProblem,
    plan: Plan,
    pairs: int,
    rival: Rival | None = None,
    beyond_noise: bool = False,
) -> Plan:
    """``plan``, done on the strength of its estimate over ``pairs`` pairs, made ambiguous when
    the estimate cannot rule out a ``rival``; or when it lies almost as near another grid pose:
    within :data:`EDGE_MARGIN_STEPS` grid steps of angle (``d₂ − d₁``, the angles to the second
    nearest and the nearest grid pose) of the boundary between the two, where the estimate's own
    error (a few tenths of a degree, more from a single view) decides which is nearest; or when
    that boundary lies within :data:`SIGMA_MARGIN` of the estimate's σ; or when fewer than
    :data:`MIN_ESTIMATE_PAIRS` pairs leave that error larger; or when just that many pairs
    match ``beyond_noise`` (module docstring), the second nearest pose's view then settling it.
    The other pose becomes an alternative.

    Measured with the general model on generated scenes (``cosmos bench --scenes demo
    --random-scenes 3 --onboard none --n 8 --seed 97 --strategies reprojection``, 288
    searches, one run each way): its one confirmed wrong answer (a moved object; θ 80° answered
    75° over three pairs at RMS 5.8 px, edge noise 2.5 px) was found and confirmed at θ 80°
    by one render more; no other search changed. On seed 7 (``--random-scenes 5 --n 5``, 300
    searches, which set the margins above): found 290 either way, none confirmed wrong either
    way, confirmed right 221 → 220 (a photo target's, left unconfirmed), renders 1,189 →
    1,195. On the built-in scenes (``cosmos bench --scenes demo,garden --n 5 --strategies
    reprojection --seed 3``, 80 searches) nothing changed."""
    if rival is not None and rival.flat != plan.next_flat:
        other = problem.grid.unflat(rival.flat)
        return replace(
            plan,
            ambiguous=True,
            alternatives=(*plan.alternatives, (rival.flat, rival.score)),
            reason=f"{plan.reason}; ambiguous: {rival.why}: it cannot tell this grid pose from "
            f"lat {other.lat} lon {other.lon}",
            checks=_more_checks(plan, (rival.flat,)),
            vindicated=plan.vindicated and rival.settled_by_views,
        )
    est = plan.estimate
    if est is None or not math.isfinite(est.theta_deg + est.phi_deg):
        return plan
    grid = problem.grid
    units = _units(grid)
    point = pose_to_cartesian(est.theta_deg, est.phi_deg).reshape(3)
    angles = np.degrees(np.arccos(np.clip(units @ point, -1.0, 1.0)))
    nearest, second = (int(i) for i in np.argsort(angles, kind="stable")[:2])
    margin = float(angles[second] - angles[nearest])
    few = pairs < MIN_ESTIMATE_PAIRS
    sigma = est.sigma_deg if est.sigma_deg is not None else 0.0
    wide = margin < 2.0 * SIGMA_MARGIN * sigma
    strained = beyond_noise and pairs <= MIN_ESTIMATE_PAIRS
    if nearest != plan.next_flat or (
        margin >= EDGE_MARGIN_STEPS * grid.angle_step_deg and not few and not wide and not strained
    ):
        return plan
    other = grid.unflat(second)
    residual = est.residual_px if est.residual_px is not None else 0.0
    # The grid poses the estimate's error may reach: the nearer boundary's, and those within
    # the σ band. Few pairs leave it wider than any band: no view settles that.
    band = np.flatnonzero(angles - angles[nearest] < 2.0 * SIGMA_MARGIN * sigma)
    reach = tuple(dict.fromkeys([second, *(int(f) for f in band if f != nearest)]))
    why = (
        f"only {pairs} pair(s) support the estimate θ = {est.theta_deg:.2f}°, "
        f"φ = {est.phi_deg:.2f}°: too few to tell this grid pose from lat {other.lat} "
        f"lon {other.lon}"
        if few
        else f"the views differ by more than their edge noise, and {pairs} pairs alone "
        f"support the estimate θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}°: it may as "
        f"well lie nearer lat {other.lat} lon {other.lon}"
        if strained and not wide and margin >= EDGE_MARGIN_STEPS * grid.angle_step_deg
        else f"the refined pose θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° lies almost "
        f"as near lat {other.lat} lon {other.lon} ({margin:.2f}° nearer this one)"
        if not wide
        else f"the refined pose θ = {est.theta_deg:.2f}°, φ = {est.phi_deg:.2f}° (σ "
        f"{sigma:.2f}°) lies within {SIGMA_MARGIN:g} σ of the boundary with lat {other.lat} "
        f"lon {other.lon}"
    )
    return replace(
        plan,
        ambiguous=True,
        alternatives=(*plan.alternatives, (second, float(residual))),
        reason=f"{plan.reason}; ambiguous: {why}",
        checks=_more_checks(plan, None if few else reach),
    )


def _more_checks(plan: Plan, flats: tuple[int, ...] | None) -> tuple[int, ...] | None:
    """The checks of ``plan`` made ambiguous by one more cause, which the views of ``flats``
    settle (None: no view does)."""
    if flats is None or (plan.ambiguous and plan.checks is None):
        return None
    return tuple(dict.fromkeys((*(plan.checks or ()), *flats)))
