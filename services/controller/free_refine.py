"""A free search's dense refinement: the render that confirmed a pose, refined against the
target image (the optimizer's ``POST /refine-pose``), and the answer that says how it went.

The render at the pose came with its depth (one renderer call: colours, depth, object ids), so
the refinement costs no render: the optimizer fits the pose (and, when the photo's intrinsics
were not given, the focal length) so that the render's edges, moved with the pose through
their depth, fall on the target's edges.

The answer's pose is the refined one only when the optimizer ``accepted`` the fit (it converged
and moved the pose plausibly); the box pose is then kept beside it (``box_pose``). Otherwise,
or when the optimizer refused the request or stayed away, the box pose stays the answer and the
reason says why. The status is never changed: an ambiguous answer stays ambiguous, whatever
the fit.
"""

from __future__ import annotations

import logging

from pydantic import ValidationError

from services.common.contracts.free import FreePose, nearest_grid_pose
from services.common.contracts.refine import RefinePoseRequest, RefinePoseResponse
from services.common.contracts.search import Search, SearchResult
from services.common.geometry.free_camera import direction_pose
from services.common.geometry.grid import HemisphereGrid
from services.controller.failures import SearchFailed
from services.controller.outages import OutagePolicy
from services.controller.stages import Stages

__all__ = ["refine_by_render", "refined_result"]

_log = logging.getLogger("cosmos.controller")


async def refine_by_render(
    stages: Stages,
    outages: OutagePolicy,
    search: Search,
    image: bytes,
    pose: FreePose,
    archive: bytes,
) -> RefinePoseResponse | str:
    """``pose`` refined against the target ``image`` by the render ``archive`` at it; why not
    (a sentence) when the optimizer refused the request, stayed away or answered out of
    contract: the search keeps its box pose then, it does not fail."""
    request = RefinePoseRequest(scene=search.scene, pose=pose, fit_focal=search.intrinsics is None)
    try:
        return await outages.call(
            search.id, lambda: stages.refine_pose(request, image, archive, search.id)
        )
    except SearchFailed as exc:
        _log.warning("search %s: no dense refinement: %s", search.id, exc)
        return f"no dense refinement ({exc.problem.detail or exc.problem.title})"
    except ValidationError as exc:
        _log.warning("search %s: the optimizer's refinement is out of contract: %s", search.id, exc)
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
