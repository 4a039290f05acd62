"""A photo searched without its lens whose edges bend as a distorting lens's: its answer,
fitted as a pinhole's, is not confirmed.

A free search given no lens distortion, and reading none from the photo, fits the pose (and,
without the intrinsics, the focal length) of a pinhole camera. Survey drones shoot through wide
lenses with barrel distortion, and a pinhole's pose fitted to such a photo can agree with its
render box by box while 5 % of the radius off. So the optimizer's dense fit checks the lens once
more from the same render: the pose, the focal length and OpenCV's radial ``k1`` fitted together
(``DenseReport.lens``), judged to bend (``LensBend.bends``) when ``k1`` moves the farthest
explained edge points by at least 2 pixels of the fit and lies at least 4 of its standard
deviations from 0 (:mod:`services.optimizer.lens_pose`, where the thresholds are measured).

Such an answer is ``ambiguous``, never confirmed, and its reason gives the fitted ``k1`` and what
to give. Its pose is the one the lens check fitted with that ``k1`` (``lens_pose``: intrinsics
``estimated``, the lens ``k1`` alone), the pinhole's kept as ``box_pose`` when there was none.
``python -m benchmarks.drone_lens --seeds 11,12`` (32 photos through barrel lenses, one run):
searched with nothing read, 22 within 5 %/2° and 16 within 2 %/1° where the pinhole answers
were 21 and 7, and none confirmed where 5 were, one of them 6.5 % of the radius off; with the
EXIF's focal length alone 28 and 18 where they were 24 and 9; with the exact intrinsics but not
the lens 31 and 26, 2 confirmed and right (``docs/EVALUATION.md``).

That pose was fitted through the lens from a pinhole's render, whose silhouettes were seen
through no lens and from the pinhole's pose. While renders remain, it is rendered once more
through its lens and refitted from there, ``k1`` started at its estimate (``fit_lens``), and
that fit answers when it is accepted and still bends (:func:`through_lens`). ``python -m
benchmarks.drone_lens --seeds 11,12`` since: with the EXIF's focal length alone 30 within 5 %/2°
and 19 within 2 %/1° (28 and 18 before), with nothing read 26 and 21 (22 and 16), none
confirmed, one render more each (``docs/EVALUATION.md``).

A search answered from its recorded iterations after a stop (:func:`lens_unchecked`) has no
render left to fit by, so no lens check: unless it was given the lens, it is not confirmed.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable

from services.common.contracts.free import FreePose, PhotoIntrinsics
from services.common.contracts.refine import RefinePoseRequest, RefinePoseResponse
from services.common.contracts.search import Search, SearchResult, StageTimings
from services.common.geometry.grid import HemisphereGrid
from services.controller.failures import SearchFailed
from services.controller.free_iterations import timed
from services.controller.free_verdict import unconfirmed_at

__all__ = [
    "lens_bent",
    "lens_unchecked",
    "lens_refit_request",
    "refit_through_lens",
    "through_lens",
    "with_lens_doubt",
]

_log = logging.getLogger("cosmos.controller")


def lens_bent(outcome: RefinePoseResponse | str | None) -> RefinePoseResponse | None:
    """The dense fit's ``outcome`` when its lens check says the target's edges bend as a
    lens's (module docstring), else None (no fit, no check, or no bend)."""
    if not isinstance(outcome, RefinePoseResponse):
        return None
    lens = outcome.fit.lens
    return outcome if lens is not None and lens.bends else None


def lens_refit_request(search: Search, pose: FreePose) -> RefinePoseRequest:
    """The refinement of a lens check's ``pose`` by its own render, made through the lens it
    estimated: ``k1`` fitted again (``fit_lens``), and the focal length too unless the user gave
    it (the check freed an EXIF's: :mod:`services.optimizer.lens_pose`)."""
    given = search.intrinsics is not None and search.intrinsics.source != "exif"
    return RefinePoseRequest(scene=search.scene, pose=pose, fit_focal=not given, fit_lens=True)


def through_lens(first: RefinePoseResponse, again: RefinePoseResponse | str) -> RefinePoseResponse:
    """The outcome that answers a bent search: ``again``, the fit from a render through the
    lens the ``first`` fit's check estimated, when it was accepted and still bends (its
    ``lens_pose`` fitted from there), else ``first``."""
    if isinstance(again, str) or not again.fit.accepted or again.lens_pose is None:
        return first
    return first if lens_bent(again) is None else again


async def refit_through_lens(
    bent: RefinePoseResponse,
    search: Search,
    render: Callable[[FreePose], Awaitable[tuple[bytes, float]]],
    refine: Callable[[RefinePoseRequest, bytes], Awaitable[RefinePoseResponse | str]],
) -> tuple[RefinePoseResponse, StageTimings | None]:
    """``bent``'s lens pose rendered through its lens (``render``: the archive and its
    milliseconds) and refitted from there (``refine``), lens and all: the outcome that answers
    (:func:`through_lens`) and the render's milliseconds. A render that fails (the outage
    policy's budget spent) leaves ``bent`` answering, as without that render: the search keeps
    its doubt and loses nothing."""
    pose = bent.lens_pose
    assert pose is not None
    try:
        archive, render_ms = await render(pose)
    except SearchFailed as exc:
        _log.warning("search %s: no render through the estimated lens: %s", search.id, exc)
        return bent, None
    again, refine_ms = await timed(refine(lens_refit_request(search, pose), archive))
    total = render_ms + refine_ms
    return through_lens(bent, again), StageTimings(
        render_ms=render_ms, refine_ms=refine_ms, total_ms=total
    )


def with_lens_doubt(
    result: SearchResult, outcome: RefinePoseResponse, grid: HemisphereGrid
) -> SearchResult:
    """``result`` (a free search's, fitted as a pinhole's) answered at the pose ``outcome``'s
    lens check fitted (when it gave one: the pinhole's pose then leads its alternatives, as
    either may be the right one), not confirmed, ``ambiguous``, its reason saying that the
    photo's edges bend and what to give."""
    free, bend = result.free, outcome.fit.lens
    if free is None or bend is None:
        return result
    pose = outcome.lens_pose
    taken = (
        "the answer is the pose fitted with that k1, the pinhole's its first alternative"
        if pose
        else "the pinhole pose is kept"
    )
    if pose is None and bend.cost_drop is not None:
        taken += f" (that k1 removes {bend.cost_drop:.1%} of the pinhole fit's edge misfit)"
    reason = (
        f"{result.reason}; but the photo's edges bend as a distorting lens's do (the fit puts "
        f"its radial k1 at {bend.k1:.3f} ± {bend.k1_sigma:.3f}, moving the edges near the "
        f"frame's corners by {bend.bend_px:.1f} px), and the pose was fitted without a lens: "
        f"{taken}, not confirmed; give the lens's distortion (k1, k2, p1, p2) and intrinsics, "
        "or a photo whose XMP states its calibration, to confirm it"
    )
    doubted = unconfirmed_at(result, reason, grid, pose)
    if pose is None or doubted.free is None:
        return doubted
    alternatives = (free.pose, *doubted.free.alternatives)
    return doubted.model_copy(
        update={"free": doubted.free.model_copy(update={"alternatives": alternatives})}
    )


def lens_unchecked(
    result: SearchResult, known: PhotoIntrinsics | None, grid: HemisphereGrid
) -> SearchResult:
    """``result`` of a free search answered from its recorded iterations after a stop, with no
    render left to fit (so no lens check): not confirmed unless the search ``known``-ly had its
    lens, since a distorted photo's pinhole pose can agree with its render box by box."""
    if not result.confirmed or (known is not None and known.distortion is not None):
        return result
    reason = (
        f"{result.reason}; not confirmed: resumed after its render, the photo's edges were not "
        "checked for a distorting lens (give the lens's distortion, or search again)"
    )
    return unconfirmed_at(result, reason, grid)
