"""A free search's dense refinement: the render that confirmed a pose, refined against the
target image (the optimizer's ``POST /refine-pose``), and the answer that says how it went.

The render at the pose came with its depth (one renderer call: colours, depth, object ids), so
the refinement costs no render: the optimizer fits the pose (and, when the photo's intrinsics
were not given, the focal length) so that the render's edges, moved with the pose through
their depth, fall on the target's edges.

The answer's pose is the refined one only when the optimizer ``accepted`` the fit (it converged
and moved the pose plausibly); the box pose is then kept beside it (``box_pose``). Otherwise,
or when the optimizer refused the request or stayed away, the box pose stays the answer and the
reason says why. So it does when a confirmed pose was turned away by the fit with little
support from the image (:func:`edges_unvouched`): the render checked the box pose, not the
fit. The status changes in one case only: a pose that the boxes pinned only loosely, whose
render agreed, is confirmed when the intrinsics were given and the fit leaves nearly all the
render's edges on the target's (:func:`edges_pin`). Any other ambiguous answer stays
ambiguous, whatever the fit.

Every share of edge points here is taken above the share that a pose placed at random would
leave on the target's edges (``DenseReport.share``): about the raw share on a plain target, far
less on an edge-rich one, where any pose's points find edges. The shares were measured on
rendered targets, whose chance is 1-3 %.

A fit that moved far from the render (``render_again``: it fitted the focal length far from
the render's, or moved the camera far) is rendered once more at the refined pose and refitted
from there (the first render's silhouettes, seen from the box pose, bias the fit: the focal
length, which the distance follows, and the pose). With it, free targets of generated scenes
without given intrinsics went from 76 % to 97 % within 5 %/2° (measured in-process:
``python -m cosmos.bench.free_targets``). That render counts in the answer's renders.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Coroutine
from contextlib import asynccontextmanager
from typing import Any, Final

from pydantic import ValidationError

from services.common.contracts.free import (
    EXACT_SOURCES,
    DenseReport,
    FreeAmbiguity,
    FreePose,
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.contracts.refine import (
    RefinePoseRequest,
    RefinePoseResponse,
    TargetRequest,
)
from services.common.contracts.search import Search, SearchResult, StageTimings
from services.common.geometry.free_camera import direction_pose
from services.common.geometry.grid import HemisphereGrid
from services.controller.failures import SearchFailed
from services.controller.outages import OutagePolicy
from services.controller.stages import Stages

__all__ = [
    "EDGE_SHARE",
    "PIN_SHARE",
    "FEW_EDGE_SHARE",
    "edges_agree",
    "edges_contradict",
    "edges_hold",
    "edges_pin",
    "edges_pin_pose",
    "edges_unvouched",
    "alongside",
    "ask_refinement",
    "fit_pins",
    "prepare_target",
    "refine_by_render",
    "refined_result",
    "with_extra_renders",
]

_log = logging.getLogger("cosmos.controller")

EDGE_SHARE: Final = 0.8
"""The share of a render's edge points that an accepted dense fit must leave on the target's
edges for the render to agree with the target by its edges."""


FEW_EDGE_SHARE: Final = 0.5
"""A fit that leaves fewer than this share of a render's edge points on the target's edges
contradicts the render's box agreement (:func:`edges_contradict`)."""
MIN_EDGE_POINTS: Final = 30
"""Fewer edge points say nothing either way (the optimizer does not fit them)."""
STRAY_START_SHARE: Final = 0.3
"""A fit that converged somewhere it may not go (not accepted) from a render that left fewer
than this share of its edge points on the target's edges contradicts the render's box
agreement too (:func:`edges_contradict`)."""


PIN_SHARE: Final = 0.9
"""The share of a render's edge points that an accepted dense fit must leave on the target's
edges to pin a pose the boxes pinned only loosely (:func:`edges_pin`)."""
MIN_PIN_POINTS: Final = 150
"""A dense fit pins a pose only with at least this many edge points: one of six unknowns to a
few dozen points can leave them all on the target's edges away from the pose. In 1,091 pinned
answers of 58 recorded free bench runs (seeds 1-5, several versions, 320- and 1280-pixel
targets), the right ones had 238 edge points or more; two 1280-pixel views of three small
objects (86 and 89 points, 94 % and 97 % of them on the target's edges) were pinned 11.5 % and
6.1 % of the radius off."""
VOUCH_TURN_DEG: Final = 1.0
"""A dense fit that turns a confirmed pose by more than this (half the turn that makes a
confirmed answer wrong)…"""
VOUCH_GAIN: Final = 1.2
"""…must explain this many times the render's edge points on the target's that the start
explained, or :data:`PIN_SHARE` of them (:func:`edges_unvouched`)."""


def edges_pin(
    outcome: RefinePoseResponse | str | None,
    known: PhotoIntrinsics | None,
    ambiguity: FreeAmbiguity | None,
) -> RefinePoseResponse | None:
    """The dense fit, when it pins a pose that the boxes pinned only ``loose``-ly (else None):
    :func:`edges_pin_pose`.

    The boxes' σ is large along a valley that the many edge points close. Not so without the
    intrinsics: distance then trades against focal length (a dolly zoom), which the edges of a
    flat layout seen from above do not resolve. Measured on four recorded runs of ``cosmos
    bench --free --scene demo --random-scenes 2 --n 8`` (seed 1 three times, seed 5 once; 480
    searches through the real stack), loose answers whose render agreed: with the intrinsics
    given, the 109 fits at or above 0.9 were all within 5 %/2°, and the misses (5.8 % and 7.2 %
    off) were at 0.87 and below; without them, a miss 39 % off was at 0.89, and earlier
    versions' misses 15-39 % off at 0.91-0.92. Rival poses (a symmetric layout, look-alikes)
    are not pinned so: a render of one cannot tell it from the others; only the renders of the
    others can (:mod:`~services.controller.free_loop`)."""
    return edges_pin_pose(outcome, known) if ambiguity == "loose" else None


def edges_pin_pose(
    outcome: RefinePoseResponse | str | None, known: PhotoIntrinsics | None
) -> RefinePoseResponse | None:
    """The dense fit, when it pins its pose (else None): it was accepted and leaves at least
    :data:`PIN_SHARE` of the render's edge points, at least :data:`MIN_PIN_POINTS` of them, on
    the target's, and the photo's intrinsics were ``known`` exactly: given or a drone's
    calibration (an EXIF focal length no render can check)."""
    return _pinned(outcome, known, MIN_PIN_POINTS)


def _pinned(
    outcome: RefinePoseResponse | str | None, known: PhotoIntrinsics | None, min_points: int
) -> RefinePoseResponse | None:
    """``outcome`` when its fit was accepted and leaves at least :data:`PIN_SHARE` of its
    ``min_points`` or more edge points on the target's, the intrinsics exact (else None)."""
    if known is None or known.source not in EXACT_SOURCES:
        return None
    if not isinstance(outcome, RefinePoseResponse):
        return None
    return outcome if fit_pins(outcome.fit, min_points) else None


def fit_pins(fit: DenseReport, min_points: int = MIN_PIN_POINTS, share: float = PIN_SHARE) -> bool:
    """Whether a dense ``fit`` pins its pose: accepted, leaving at least ``share`` of its
    ``min_points`` or more edge points on the target's."""
    return fit.accepted and fit.share() >= share and fit.edge_points >= min_points


def edges_hold(
    outcome: RefinePoseResponse | str | None, known: PhotoIntrinsics | None
) -> RefinePoseResponse | None:
    """The dense fit, when it was accepted and leaves at least :data:`PIN_SHARE` of its
    render's edge points on the target's, the photo's intrinsics given (else None): a
    ``rivals`` candidate so rendered is worth its rivals' renders, and when none of them agrees
    it is the answer, confirmed. The rivals' renders are what tell it from them.

    It took :data:`EDGE_SHARE` (a render that agrees by its edges) for a while, set on seeds
    1–5 of ``cosmos bench --free --scene demo --random-scenes 2 --n 8``, where the answers so
    confirmed at 0.78–0.89 were all within 5 %/2°. On runs that did not set it (seeds 21–23
    with ``--random-scenes 3``, both general detectors; seeds 1–4 with one fine-tuned on drone
    views: 119 answers confirmed this way), the answers at 0.80–0.90 were 33 right and 4 wrong,
    6–24 % of the radius and 4–9° off (two scenes with a moved object, two with pixel noise);
    at 0.9 and above, 82 right and none wrong. Those below are answered all the same, as
    ``ambiguous``."""
    return _pinned(outcome, known, 0)


def edges_unvouched(fit: DenseReport) -> bool:
    """Whether an accepted dense fit turned the pose by more than :data:`VOUCH_TURN_DEG` with
    little support from the image: fewer than :data:`VOUCH_GAIN` times the edge points the start
    explained, and fewer than :data:`PIN_SHARE` of them in all. Measured on seven recorded runs
    of ``cosmos bench --free --scene demo --random-scenes 2 --n 8`` (seeds 1–6, and 5 again;
    840 searches): of the 225 confirmed answers refined so, this holds for 5: the only two
    confirmed wrong ones (the demo under another light: its box pose 0.2–0.3 % off, turned
    2.7° and 4.3° while explaining 3 % more edges) and 3 right ones. Those answers were
    demoted to ``ambiguous`` with the fit's pose; the box pose, which their renders checked,
    is kept and confirmed instead: on seeds 1–3 again (2026-12-05) this held for 3 answers, whose
    box poses were all within 2.1 %/1.2° and two of them nearer the truth than the fit's
    (0.3 %/0.1° against 3.4 %/2.6°; 2.1 %/0.7° against 4.3 %/1.3°)."""
    if not fit.accepted or fit.moved_rotation_deg <= VOUCH_TURN_DEG:
        return False
    gained = fit.share() >= VOUCH_GAIN * max(fit.share(fit.start_inliers), 0.0)
    return not gained and fit.share() < PIN_SHARE


def edges_contradict(outcome: RefinePoseResponse | str | None) -> bool:
    """Whether the dense fit from a render says that the render does not show the target,
    whatever its boxes say, from :data:`MIN_EDGE_POINTS` edge points or more:

    * it did not converge, and left fewer than :data:`FEW_EDGE_SHARE` of them on the target's
      edges. Measured through the real stack (``cosmos bench --free --scene demo
      --random-scenes 2 --n 8 --seed 1``): the renders whose boxes agreed and whose fits did
      not converge were 5 poses 20-100° off (a moved object let a wrong pose pair every box)
      and 2 near ones, at shares 0.26-0.45; the correct poses' fits leave 0.52-1.0;
    * or it converged far from the render (not accepted), which had left fewer than
      :data:`STRAY_START_SHARE` of them on the target's: the image is explained elsewhere.
      Over 1,120 searches of the free bench's recorded runs (seeds 1-6, and 2-3 onboarded),
      the 42 answers whose fit ended so from below that share were all 30-280 % of the radius
      off; of the 49 from above it, 10 were within 5 % (under another light, at 0.42-0.47). On
      seed 3 a demo view's wrong pose paired every box within 0.38 px at a share of 0.065 and
      was answered 200 % off; the pose the search had rendered before it was 0.2 % off.

    A fit that never ran (the optimizer away) says nothing."""
    if not isinstance(outcome, RefinePoseResponse):
        return False
    fit = outcome.fit
    if fit.edge_points < MIN_EDGE_POINTS:
        return False
    if not fit.converged:
        return fit.share() < FEW_EDGE_SHARE
    return not fit.accepted and fit.share(fit.start_inliers) < STRAY_START_SHARE


def edges_agree(outcome: RefinePoseResponse | str | None) -> bool:
    """Whether a render agrees with the target by its edges: the dense fit from it was
    accepted and leaves at least :data:`EDGE_SHARE` of its edge points within 2 px of a target
    edge (the image explains the pose, whatever a detector names its objects)."""
    if not isinstance(outcome, RefinePoseResponse) or not outcome.fit.accepted:
        return False
    return outcome.fit.share() >= EDGE_SHARE


@asynccontextmanager
async def alongside(work: Coroutine[Any, Any, None] | None) -> AsyncIterator[None]:
    """``work`` (if any) run as a task while the block runs, cancelled if the block ends
    first."""
    task = asyncio.create_task(work) if work is not None else None
    try:
        yield
    finally:
        if task is not None:
            task.cancel()


def _stated(search: Search) -> bool:
    """Whether the search's focal length was stated by its photo's EXIF, not given: its
    refinements check it (:mod:`~services.controller.exif_check`)."""
    return search.intrinsics is not None and search.intrinsics.source == "exif"


async def prepare_target(
    stages: Stages, search: Search, image: bytes, film: tuple[int, int]
) -> None:
    """Ask the optimizer to make the target ``image`` ready for the refinements on the renders'
    ``film`` (``POST /refine-pose/target``), so that the first one, after the box solve and the
    render, finds its grey image and distance maps made. Best effort: a refinement makes them
    itself otherwise, so a failure is only logged; no outage is waited out for it.

    It runs beside the first render: beside the box solve, in the optimizer's own process, it
    moved 12 ms from the refinement to the solve (``cosmos bench --free --scene demo
    --random-scenes 2 --n 8 --seed 1``). Beside the render, the first refinement took 63 → 51 ms
    and the median one-render search 205 → 195 ms on that bench; with 4000 x 3000 JPEG photos of
    the demo (through ``cosmos up``, 18 searches a run) the first refinement took 38 ms against
    77 ms before the maps were kept and made ahead, the median search 279 ms against 294-333."""
    request = TargetRequest(film=film, fit_focal=search.intrinsics is None or _stated(search))
    try:
        await stages.prepare_target(request, image, search.id)
    except Exception as exc:  # the search goes on whatever this says
        _log.info("search %s: the target was not made ready ahead: %s", search.id, exc)


async def refine_by_render(
    stages: Stages,
    outages: OutagePolicy,
    search: Search,
    image: bytes,
    pose: FreePose,
    archive: bytes,
) -> RefinePoseResponse | str:
    """``pose`` refined against the target ``image`` by the render ``archive`` at it (its focal
    length checked too when the photo's EXIF stated it); why not (a sentence) when the
    optimizer refused the request, stayed away or answered out of contract: the search keeps
    its box pose then, it does not fail."""
    request = RefinePoseRequest(
        scene=search.scene,
        pose=pose,
        fit_focal=search.intrinsics is None,
        check_focal=_stated(search),
    )
    return await ask_refinement(stages, outages, search.id, request, image, archive)


async def ask_refinement(
    stages: Stages,
    outages: OutagePolicy,
    search_id: str,
    request: RefinePoseRequest,
    image: bytes,
    archive: bytes,
) -> RefinePoseResponse | str:
    """The optimizer's refinement of ``request``'s pose against the target ``image`` by the
    render ``archive``; why not (a sentence) when it refused, stayed away or answered out of
    contract."""
    try:
        return await outages.call(
            search_id, lambda: stages.refine_pose(request, image, archive, search_id)
        )
    except SearchFailed as exc:
        _log.warning("search %s: no dense refinement: %s", search_id, exc)
        return f"no dense refinement ({exc.problem.detail or exc.problem.title})"
    except ValidationError as exc:
        _log.warning("search %s: the optimizer's refinement is out of contract: %s", search_id, exc)
        return "no dense refinement (the optimizer's answer does not fit this controller)"


def refined_result(
    result: SearchResult, outcome: RefinePoseResponse | str, grid: HemisphereGrid
) -> SearchResult:
    """``result`` (a free search's, from its box pose) with the refinement's ``outcome``
    (module docstring)."""
    free = result.free
    if free is None:
        return result
    if isinstance(outcome, str):
        return result.model_copy(update={"reason": f"{result.reason}; {outcome}: the box pose"})
    fit = outcome.fit
    if not fit.accepted:
        reason = f"{result.reason}; the box pose is kept: {fit.reason}"
        return result.model_copy(
            update={"reason": reason, "free": free.model_copy(update={"dense": fit})}
        )
    if result.confirmed and edges_unvouched(fit):
        reason = (
            f"{result.reason}; the box pose, which the render checked, is kept: the fit "
            f"turned it {fit.moved_rotation_deg:.1f}° without the image's firm support "
            f"({fit.start_inliers} → {fit.inliers} of {fit.edge_points} edge points on the "
            f"target's; {VOUCH_GAIN:g} times as many, or {PIN_SHARE:.0%} of them, would vouch "
            "for it)"
        )
        return result.model_copy(
            update={"reason": reason, "free": free.model_copy(update={"dense": fit})}
        )
    pose = outcome.pose
    nearest = nearest_grid_pose(pose.position, grid)
    answer = free.model_copy(
        update={"pose": pose, "box_pose": free.pose, "dense": fit, "nearest_grid": nearest}
    )
    return result.model_copy(
        update={
            "pose": nearest,
            "refined_pose": direction_pose(pose.position),
            "reason": f"{result.reason}; {fit.reason}",
            "free": answer,
        }
    )


def with_extra_renders(
    result: SearchResult,
    timings: StageTimings | None,
    followed: int = 0,
    lens: StageTimings | None = None,
) -> SearchResult:
    """``result`` with the renders that are no iteration of their own, said in its reason:
    the one spent on refitting (module docstring; its ``timings``, None when none was made),
    the ``followed`` ones at candidates' dense fits whose renders disagreed
    (:func:`~services.controller.free_iterations.worth_following`) and the one through the lens
    a lens check estimated (``lens``: :mod:`~services.controller.lens_check`)."""
    free = result.free
    made = [t for t in (timings, lens) if t is not None]
    if free is None or (not made and not followed):
        return result
    extra = followed + len(made)
    reason = result.reason
    if followed:
        reason += f"; {followed} render(s) at a candidate's dense fit, its own render disagreeing"
    if timings is not None:
        reason += "; refitted by one more render at the refined pose"
    if lens is not None:
        reason += "; refitted through the estimated lens by one more render"
    return result.model_copy(
        update={
            "renders": result.renders + extra,
            "reason": reason,
            "free": free.model_copy(update={"renders": free.renders + extra}),
            "refit_timings": _summed(made) if made else None,
        }
    )


def _summed(timings: list[StageTimings]) -> StageTimings:
    """The milliseconds of several renders after the iterations, stage by stage."""
    return StageTimings(
        render_ms=sum(t.render_ms for t in timings),
        detect_ms=sum(t.detect_ms for t in timings),
        optimize_ms=sum(t.optimize_ms for t in timings),
        refine_ms=sum(t.refine_ms for t in timings),
        total_ms=sum(t.total_ms for t in timings),
    )
