"""A free search's rendered candidate as the search records it: which candidate it was, what
its render showed, the iteration that says so (with its timings) and why it agreed or not.
"""

from __future__ import annotations

import time
from collections.abc import Awaitable
from dataclasses import dataclass, replace
from typing import TypeVar

from services.common.contracts.detect import DetectResponse
from services.common.contracts.free import FreePose, nearest_grid_pose
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.search import Iteration, StageTimings
from services.common.geometry.free_camera import FreeCamera, direction_pose
from services.common.geometry.grid import HemisphereGrid
from services.controller.free_match import FreeMatch
from services.controller.free_refine import edges_agree, edges_contradict

__all__ = [
    "Seen",
    "Step",
    "iteration_of",
    "render_agrees",
    "spent",
    "timed",
    "timings_of",
    "worth_following",
]

T = TypeVar("T")


@dataclass(frozen=True)
class Step:
    """Which candidate an iteration renders: its index, of how many, whether the optimizer's
    answer was ambiguous, the optimizer's milliseconds spent for it (the first's), whether
    the search renders the next candidate even when this one agrees (its rivals are checked),
    and, when the render shown is the one at the candidate's dense fit, its first render
    having disagreed (:func:`worth_following`), the camera of that first render."""

    index: int
    count: int
    ambiguous: bool
    optimize_ms: float
    goes_on: bool = False
    followed: FreeCamera | None = None


@dataclass(frozen=True)
class Seen:
    """A candidate's render: the camera rendered, its archive (colours, depth, object ids),
    its detections, how they compare with the target's, render, detect and dense refinement
    milliseconds (the last two side by side)."""

    camera: FreeCamera
    archive: bytes
    found: DetectResponse
    check: FreeMatch
    render_ms: float
    detect_ms: float
    refine_ms: float


async def timed(work: Awaitable[T]) -> tuple[T, float]:
    """``work``'s result and the milliseconds it took."""
    started = time.perf_counter()
    result = await work
    return result, (time.perf_counter() - started) * 1000


def timings_of(seen: Seen, optimize_ms: float = 0.0) -> StageTimings:
    """A render's milliseconds: the optimizer's before it, the render, then detection and dense
    fit side by side."""
    slower = max(seen.detect_ms, seen.refine_ms)
    return StageTimings(
        render_ms=seen.render_ms,
        detect_ms=seen.detect_ms,
        optimize_ms=optimize_ms,
        refine_ms=seen.refine_ms,
        total_ms=optimize_ms + seen.render_ms + slower,
    )


def spent(shown: Seen, other: Seen) -> Seen:
    """``shown`` with ``other``'s render, detection and fit milliseconds added: the time of
    both renders of a followed candidate is its iteration's."""
    return replace(
        shown,
        render_ms=shown.render_ms + other.render_ms,
        detect_ms=shown.detect_ms + other.detect_ms,
        refine_ms=shown.refine_ms + other.refine_ms,
    )


def render_agrees(check: FreeMatch, edges: RefinePoseResponse | str | None) -> bool:
    """Whether a render agrees with the target: its boxes do and its edges do not contradict
    them, or its edges agree (:mod:`~services.controller.free_loop`, step 4)."""
    return (check.agree and not edges_contradict(edges)) or edges_agree(edges)


def worth_following(check: FreeMatch, edges: RefinePoseResponse | str | None) -> bool:
    """Whether to render once more at a candidate's dense fit: its render disagreed with the
    target, yet the fit from it was accepted (it converged and moved plausibly, its boxes kept
    by the target's). The render said the candidate is not the target's pose; the fit found
    one near it that the target's edges explain, which a render there can check.

    Seed 3 of ``cosmos bench --free --scene demo --random-scenes 2 --n 8`` had a demo view
    whose box pose, 12 % of the radius and 6° off, left one object where the target does not
    show it; its fit took it to 0.2 % and 0.1°, but left 0.67 of its edge points on the
    target's, short of agreeing by its edges (0.8): the search rendered 3 more alternatives, none
    agreeing, and answered the fitted pose unconfirmed.

    A fit the optimizer calls a ``lead`` (it moved too far to be accepted, but most of its
    edges ended on the target's) is rendered the same way: the render there, not the fit,
    says whether it found the pose."""
    if render_agrees(check, edges) or not isinstance(edges, RefinePoseResponse):
        return False
    return edges.fit.accepted or edges.fit.lead


def iteration_of(
    step: Step,
    pose: FreePose,
    following: FreePose | None,
    seen: Seen,
    grid: HemisphereGrid,
    edges: RefinePoseResponse | str | None,
) -> Iteration:
    """The iteration that rendered ``pose`` (its dense fit ``edges``), going on to
    ``following`` if its render disagreed or the step goes on regardless."""
    nearest = nearest_grid_pose(pose.position, grid)
    check = seen.check
    agreed = render_agrees(check, edges)
    goes_on = following is not None and (not agreed or step.goes_on)
    next_pose = nearest_grid_pose(following.position, grid) if goes_on and following else None
    at = " at its dense fit (its own render disagreed)" if step.followed is not None else ""
    reason = f"pose {step.index + 1} of {step.count}{at}: {_agreement(check, edges)}"
    if agreed and goes_on:
        reason += "; its rivals are rendered next"
    return Iteration(
        index=step.index,
        pose=nearest,
        image_size=seen.found.image_size,
        detections=seen.found.detections,
        timings=timings_of(seen, step.optimize_ms),
        estimate=direction_pose(pose.position),
        estimate_grid=nearest,
        confidence=pose.confidence * check.match.score,
        ambiguous=step.ambiguous,
        next_pose=next_pose,
        done=agreed and not goes_on,
        agrees=agreed,
        reason=reason,
        match=check.match,
        detector_sha256=seen.found.model.sha256,
        camera=seen.camera,
        candidate_camera=step.followed,
    )


def _agreement(check: FreeMatch, edges: RefinePoseResponse | str | None) -> str:
    m = check.match
    if check.agree and edges_contradict(edges):
        assert isinstance(edges, RefinePoseResponse)
        fit = edges.fit
        return (
            f"its render's boxes agree with the target's (RMS {m.rms_px or 0.0:.2f} px), but "
            f"its edges do not: {fit.inliers} of {fit.edge_points} on the target's after the "
            "dense fit"
        )
    if check.agree:
        return f"its render agrees with the target box by box (RMS {m.rms_px or 0.0:.2f} px)"
    boxes = (
        f"{len(check.missing)} paired object(s) not seen where the target shows them "
        f"({m.pairs} seen again)"
    )
    if edges_agree(edges):
        assert isinstance(edges, RefinePoseResponse)
        fit = edges.fit
        return (
            f"its render's boxes disagree with the target's ({boxes}), but its edges agree: "
            f"{fit.inliers} of {fit.edge_points} on the target's after the dense fit"
        )
    said = f"its render disagrees with the target: {boxes}"
    if isinstance(edges, RefinePoseResponse):
        fit = edges.fit
        return f"{said}; {fit.inliers} of {fit.edge_points} edges on the target's ({fit.reason})"
    return said
