"""From a free search's rendered candidates to its answer: which one to answer, and whether
the renders confirm it (:mod:`~services.controller.free_loop`'s docstring says when).

A candidate *agrees* when its render does (box by box, its edges not contradicting, or by its
edges). The answer is the agreeing candidate that explains the target best (the most edges on
the target's after an accepted fit, then at its own render's pose, then the box match), else
the candidate that explains it best. It is ``found`` and confirmed only when the optimizer
found a unique pose, or its edges pin a pose the boxes pinned loosely, or it is the only one
of a ``rivals`` answer's candidates whose render agrees (every candidate rendered, the
intrinsics given; agreeing candidates whose fits end at one pose count once:
:data:`SAME_POSE_SHARE`) and its edges hold (:func:`~.free_refine.edges_hold`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from services.common.contracts.free import (
    EXACT_SOURCES,
    DenseReport,
    FreeAmbiguity,
    FreeAnswer,
    FreePose,
    FreePoseResponse,
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.contracts.refine import RefinePoseResponse
from services.common.contracts.search import Iteration, SearchResult
from services.common.geometry.free_camera import (
    direction_pose,
    rotation_angle_deg,
    rotation_of_quaternion,
)
from services.common.geometry.grid import HemisphereGrid

__all__ = [
    "SAME_POSE_DEG",
    "SAME_POSE_SHARE",
    "STEEP_PITCH_DEG",
    "Verdict",
    "agrees",
    "checks_rivals",
    "choice",
    "free_result",
    "others_standing",
    "unconfirmed_at",
]

STEEP_PITCH_DEG: Final = 60.0
"""From this pitch down (90°: nadir) a target's edges hardly tell distance from focal length:
``python -m benchmarks.focal_valley`` (seeds 1 and 2, 48 targets) found that a focal length 5 %
off raises the best pose's edge cost by 3–6 % at 60–89° and at the nadir, by 24–83 % at
10–60°."""
SAME_POSE_SHARE: Final = 0.02
"""Two rendered candidates whose poses, each refined by its own render (the box pose when its
fit was not accepted), end within this share of the scene's radius…"""
SAME_POSE_DEG: Final = 1.0
"""…and this many degrees of each other are one pose (the free bench's tightest tolerance):
rivals that their renders' fits bring together are not a symmetric layout. On seeds 1–3 of
``cosmos bench --free --scene demo --random-scenes 2 --n 8`` (360 searches), 16 answers had
their rivals rendered; in 5 a second render agreed too, and the fits brought 3 of those to the
first one's pose."""


def _explains(iteration: Iteration, edges: RefinePoseResponse | str | None) -> tuple[float, ...]:
    """How well a rendered candidate explains the target: the share of its render's edges on
    the target's after an accepted dense fit, above chance (0 without one); then that share at
    the candidate's own pose, where its render was made (the pose answered when its fit is not
    accepted); then its box match score.

    The image's edges come before the detector's boxes: on seed 2 of ``cosmos bench --free
    --scene demo --random-scenes 2 --n 8``, a demo view under another light had neither render's
    fit accepted; the box pose 1.6 % off matched the target's boxes at 5.8 px, a pose 89 % off
    at 0.7 px, which was answered, though its render left fewer of its edge points on the
    target's edges (290 of 842 after its fit, 458 of 900 for the other); it is now the box
    pose. Over seeds 1–5 (600 searches, one run each way) that was the one answer this brought
    within 5 %/2°; 82 others, all wrong and ``ambiguous`` either way, became other wrong
    poses (40 of them nearer the truth, median 1.12 → 1.00 radii); nothing else changed."""
    share = start = 0.0
    if isinstance(edges, RefinePoseResponse) and edges.fit.edge_points > 0:
        fit = edges.fit
        start = fit.share(fit.start_inliers)
        share = fit.share() if fit.accepted else 0.0
    return (share, start, iteration.match.score if iteration.match else 0.0, -iteration.index)


def agrees(iteration: Iteration) -> bool:
    """Whether a rendered candidate's render agreed (an older record says so by ``done``)."""
    return iteration.agrees if iteration.agrees is not None else iteration.done


def choice(
    history: list[Iteration], edges: dict[int, RefinePoseResponse | str]
) -> tuple[Iteration, bool]:
    """The rendered candidate to answer, and whether its render agreed: the agreeing one that
    explains the target best, else the one that explains it best (:func:`_explains`)."""
    agreeing = [it for it in history if agrees(it)]
    pool = agreeing or history
    return max(pool, key=lambda it: _explains(it, edges.get(it.index))), bool(agreeing)


def checks_rivals(answer: FreePoseResponse, known: PhotoIntrinsics | None) -> bool:
    """Whether the search may render a ``rivals`` answer's other poses after one agrees: only
    when their renders can settle it, the intrinsics exact (it does when the agreeing render's
    fit pins its pose: :func:`~.free_refine.edges_pin_pose`)."""
    exact = known is not None and known.source in EXACT_SOURCES
    return answer.ambiguity == "rivals" and exact


def _final_pose(
    k: int, candidates: list[FreePose], edges: dict[int, RefinePoseResponse | str]
) -> FreePose:
    """Candidate ``k``'s pose as its render's accepted fit left it, else its box pose."""
    outcome = edges.get(k)
    if isinstance(outcome, RefinePoseResponse) and outcome.fit.accepted:
        return outcome.pose
    return candidates[k]


def _same_pose(a: FreePose, b: FreePose, radius: float) -> bool:
    """Within :data:`SAME_POSE_SHARE` of ``radius`` and :data:`SAME_POSE_DEG` of each other."""
    turn = rotation_angle_deg(
        rotation_of_quaternion(a.quaternion_wxyz), rotation_of_quaternion(b.quaternion_wxyz)
    )
    return math.dist(a.position, b.position) <= SAME_POSE_SHARE * radius and turn <= SAME_POSE_DEG


def others_standing(
    history: list[Iteration],
    chosen: Iteration,
    candidates: list[FreePose],
    edges: dict[int, RefinePoseResponse | str],
    radius: float,
) -> tuple[int, ...]:
    """The other candidates whose renders agree and whose poses do not end where the chosen
    one's does (:func:`_same_pose`)."""
    mine = _final_pose(chosen.index, candidates, edges)
    return tuple(
        it.index
        for it in history
        if agrees(it)
        and it.index != chosen.index
        and not _same_pose(_final_pose(it.index, candidates, edges), mine, radius)
    )


@dataclass(frozen=True)
class Verdict:
    """What the renders said of the chosen candidate: ``agreed``, ``by_edges`` (its boxes
    disagreed), ``pinned`` (its fit, when that pins a loose pose or holds the one rival left
    standing), ``ruled_out`` (every other rival's render disagreed, or its fit ended at the
    chosen pose) and ``standing`` (the other agreeing candidates that did not)."""

    agreed: bool
    by_edges: bool = False
    pinned: RefinePoseResponse | None = None
    ruled_out: bool = False
    standing: tuple[int, ...] = ()


def _unconfirmed(ambiguity: FreeAmbiguity | None, pose: FreePose) -> str:
    """Why a pose whose render agrees is not confirmed, by why the boxes left it ambiguous."""
    source = pose.intrinsics.source
    if ambiguity == "loose" and source in EXACT_SOURCES:
        return (
            "its edges do not pin the pose the boxes pinned loosely (too few of the render's "
            "edge points end on the target's)"
        )
    if ambiguity == "loose" and source == "exif":
        return (
            "no render can check the photo's EXIF focal length, which the distance of a pose "
            "the boxes pinned loosely follows"
        )
    if ambiguity == "loose":
        pitch = pose.yaw_pitch_roll_deg[1]
        steep = (
            f", and looking {pitch:.0f}° down the image itself hardly tells them apart: give "
            "the photo's intrinsics"
            if pitch >= STEEP_PITCH_DEG
            else ""
        )
        return (
            "without the photo's intrinsics a render cannot pin the pose the boxes pinned "
            f"loosely (distance trades against focal length{steep})"
        )
    if ambiguity == "focal":
        return (
            "the scene camera's field of view was assumed, and a render at another distance "
            "and focal length would agree as well"
        )
    if ambiguity == "few":
        return "other poses explain so few objects' boxes as well"
    if ambiguity == "attitude":
        return "the photo's pitch and roll (its gimbal's) say otherwise"
    return "the alternatives explain its boxes too"


def free_result(
    answer: FreePoseResponse,
    history: list[Iteration],
    grid: HemisphereGrid,
    chosen: Iteration,
    verdict: Verdict,
) -> SearchResult:
    """The search's answer from its rendered candidates (module docstring): ``chosen`` and
    what its render said (``verdict``)."""
    candidates = answer.candidates
    agreed, pinned = verdict.agreed, verdict.pinned
    pose = candidates[chosen.index]
    score = chosen.match.score if chosen.match is not None else 0.0
    confirmable = answer.status == "found" or pinned is not None
    exif = pose.intrinsics.source == "exif"
    found = agreed and confirmable and not exif
    how = "by its edges (its boxes disagree)" if verdict.by_edges else "box by box"
    also = [k + 1 for k in verdict.standing]
    if found and pinned is not None and verdict.ruled_out:
        fit = pinned.fit
        rivals = len(candidates) - 1
        reason = (
            f"found: {len(pose.correspondences)} objects paired, and {rivals} rival pose(s) "
            "explained the boxes almost as well, but their renders disagree with the target or "
            "their fits end at this pose; "
            f"the render at pose {chosen.index + 1} agrees {how}, and its edges hold: "
            f"{fit.inliers} of {fit.edge_points} on the target's after the dense fit, the "
            "intrinsics given"
        )
    elif found and pinned is not None:
        fit = pinned.fit
        reason = (
            f"found: {answer.reason.removeprefix('ambiguous: ')}; the render at the pose agrees "
            f"with the target {how}, and its edges pin the pose: {fit.inliers} of "
            f"{fit.edge_points} on the target's after the dense fit, the intrinsics given"
        )
    elif found:
        reason = f"{answer.reason}; the render at the pose agrees with the target {how}"
    elif agreed and confirmable:
        reason = (
            f"{answer.reason}; the render at the pose agrees with the target {how}, but no "
            "render can check the photo's EXIF focal length (a wrong one moves the camera along "
            "its axis, and the render agrees all the same): not confirmed; give fov_deg or the "
            "intrinsics to confirm it"
        )
    elif agreed and also:
        poses = ", ".join(str(i) for i in also)
        reason = (
            f"{answer.reason}; the render at pose {chosen.index + 1} agrees with the target "
            f"{how}, and so do the renders at pose(s) {poses}: not confirmed"
        )
    elif agreed:
        reason = (
            f"{answer.reason}; the render at pose {chosen.index + 1} agrees with the target "
            f"{how}, but {_unconfirmed(answer.ambiguity, pose)}: not confirmed"
        )
    else:
        reason = (
            f"not confirmed: no render of the {len(history)} pose(s) tried agreed with the "
            f"target, box by box or by its edges; the best was pose {chosen.index + 1} (match "
            f"score {score:.2f}); {answer.reason}"
        )
    nearest = nearest_grid_pose(pose.position, grid)
    first = {i - 1 for i in also}  # the other agreeing poses lead the alternatives
    others = sorted(
        (i for i in range(len(candidates)) if i != chosen.index), key=lambda i: i not in first
    )
    return SearchResult(
        pose=nearest,
        refined_pose=direction_pose(pose.position),
        confidence=pose.confidence * score,
        renders=len(history),
        ambiguous=not found,
        reason=reason,
        confirmed=found,
        free=FreeAnswer(
            status="found" if found else "ambiguous",
            pose=pose,
            alternatives=() if found else tuple(candidates[i] for i in others),
            nearest_grid=nearest,
            renders=len(history),
            match_rms_px=chosen.match.rms_px if chosen.match is not None else None,
        ),
    )


def unconfirmed_at(
    result: SearchResult,
    reason: str,
    grid: HemisphereGrid,
    pose: FreePose | None = None,
    dense: DenseReport | None = None,
) -> SearchResult:
    """``result`` (a free search's) made ``ambiguous`` and unconfirmed for ``reason``: answered
    at ``pose`` when one is given (the pose it had kept as ``box_pose``, the nearest grid pose
    and the direction following), with ``dense`` as its fit's report when one is given."""
    free = result.free
    if free is None:
        return result
    update: dict[str, object] = {"status": "ambiguous"}
    moved: dict[str, object] = {}
    if dense is not None:
        update["dense"] = dense
    if pose is not None:
        nearest = nearest_grid_pose(pose.position, grid)
        update |= {"pose": pose, "box_pose": free.box_pose or free.pose, "nearest_grid": nearest}
        moved = {"pose": nearest, "refined_pose": direction_pose(pose.position)}
    return result.model_copy(
        update={
            **moved,
            "reason": reason,
            "confirmed": False,
            "ambiguous": True,
            "free": free.model_copy(update=update),
        }
    )
