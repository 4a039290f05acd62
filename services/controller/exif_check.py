"""A focal length from the photo's EXIF, checked by its render's edges: when they clearly put it
elsewhere, the search answers with the focal length they fit.

A free search given no intrinsics takes the focal length its photo's EXIF states
(:mod:`~services.controller.photo_exif`), and the dense fit of its render keeps it. The
optimizer then fits the pose once more from the same render with the focal length free
(``RefinePoseRequest.check_focal``, answered as ``focal_check``). When that fit was accepted,
leaves at least :data:`CHECK_SHARE` of its edge points on the target's edges, pins the focal
length to :data:`CHECK_SIGMA` (its relative standard deviation) and ends more than
:data:`DISAGREE` from the EXIF's, the EXIF is taken to be wrong (a crop or a digital zoom it
does not state): the answer is the check's pose, its focal length ``estimated``, and its
reason says why. It stays ``ambiguous``: a focal length fitted from the image is never
confirmed (:mod:`~services.controller.free_verdict`).

Measured by ``python -m benchmarks.exif_check`` (seeds 31 and 32: 96 free targets of the demo
and of four generated scenes, each searched as if its EXIF stated the focal length 5 % or 2 %
short, right, or 2 %, 5 % or 15 % long; one run): the answers within 5 %/2° went from 0 to 31
of 96 with the EXIF 15 % long, from 27 to 42 and 26 to 40 with it 5 % off either way, and
stayed 94 of 96 each with it right or 2 % off (the rounding of a 35 mm equivalent); at a
standard deviation of 1 % one of those was lost. Most steep views keep the EXIF's focal length:
their edges do not pin it to :data:`CHECK_SIGMA`. The benchmark takes the fits as
``refine_dense`` ends them; a search also needs the optimizer to have accepted the fit.

An EXIF focal length that the check agrees with is not confirmed by it: on the same run, of
the answers whose check ended within 2 % of the EXIF's at that standard deviation, the 85 with
the EXIF right or 2 % off were all within 5 %/2°, but 9 of the 16 with it 5 % or 15 % off were
not. The check's focal length leans to the render's, which was made with the EXIF's.
"""

from __future__ import annotations

from typing import Final

from services.common.contracts.refine import FocalCheck, RefinePoseResponse
from services.common.contracts.search import SearchResult
from services.common.geometry.grid import HemisphereGrid
from services.controller.free_refine import PIN_SHARE
from services.controller.free_verdict import unconfirmed_at

__all__ = ["CHECK_SHARE", "CHECK_SIGMA", "DISAGREE", "exif_overruled", "with_checked_focal"]

DISAGREE: Final = 0.03
"""The relative difference between the EXIF's focal length and the check's beyond which the
EXIF is overruled: 1.5 times the most that rounding a 35 mm equivalent to the millimetre errs
by at 24 mm."""
CHECK_SIGMA: Final = 0.005
"""The largest relative standard deviation of the check's focal length that may overrule the
EXIF (``DenseReport.focal_sigma``, which counts the edge points as independent and understates
the error: at 1 % the measured run switched a right answer to a wrong one)."""
CHECK_SHARE: Final = PIN_SHARE
"""The share of its edge points (above chance) that the check's fit must leave on the
target's edges."""


def exif_overruled(outcome: RefinePoseResponse | str | None) -> FocalCheck | None:
    """The render's focal check when it overrules the focal length the pose states (module
    docstring), else None (no check, or one that does not)."""
    if not isinstance(outcome, RefinePoseResponse) or outcome.focal_check is None:
        return None
    check = outcome.focal_check
    fit = check.fit
    sigma = fit.focal_sigma
    if not (fit.accepted and fit.focal_fitted and sigma is not None and sigma <= CHECK_SIGMA):
        return None
    if fit.share() < CHECK_SHARE:
        return None
    ratio = check.pose.intrinsics.fx_px / outcome.pose.intrinsics.fx_px
    return check if abs(ratio - 1.0) > DISAGREE else None


def with_checked_focal(
    result: SearchResult, check: FocalCheck, stated_fx_px: float, grid: HemisphereGrid
) -> SearchResult:
    """``result`` answered at the pose of the focal ``check`` that overruled the EXIF's focal
    length of ``stated_fx_px`` pixels (:func:`exif_overruled`): ambiguous, its reason saying
    why."""
    free = result.free
    if free is None:
        return result
    pose, fit = check.pose, check.fit
    ratio = pose.intrinsics.fx_px / stated_fx_px - 1.0
    reason = (
        f"{result.reason}; but the image's edges do not bear out the photo's EXIF focal length "
        "(as after a crop or a zoom that the EXIF does not state): fitted with the pose from the "
        f"same render, they put it {abs(ratio):.1%} {'longer' if ratio > 0 else 'shorter'} (±"
        f"{fit.focal_sigma or 0.0:.1%}; {fit.inliers} of {fit.edge_points} edge points on the "
        "target's), and the answer takes theirs: not confirmed; give fov_deg or the intrinsics "
        "to confirm it"
    )
    return unconfirmed_at(result, reason, grid, pose, fit)
