"""Where a hemisphere search without a given start takes its first view: the grid pose the
optimizer predicts from the target's detections alone (``POST /start-pose``), so that the search
usually ends after that one render.

The prediction needs the target's detections, so a search without a given start detects its
target first, then asks for the pose, then renders it: one detection's latency and the
optimizer's answer (a millisecond or two once the scene's grid views are kept) come before the
first render, where a given start overlaps the target's detection with its render. Measured
with ``cosmos bench --n 20 --strategies reprojection --variants clean,offgrid`` (2 shared
cores): the time outside the stages' calls grew by 70–135 ms per search (p50 wall of the clean
searches 2.0 s → 1.0 s on demo, 4.2 s → 0.65 s on garden), for a whole render, detection and
optimizer step saved (600–1000 ms there) whenever the predicted view matches: every clean
target of both scenes ended after one render.

An unsure prediction (``ambiguous``: distant poses explain the boxes almost as well; ``failed``:
fewer than half of the target's detections pair with an object) still names the pose that
explains the boxes best, and the search starts there: it is the likeliest pose the target gives,
where a drawn start is uniformly random: on 5 generated scenes with the general detector (108
targets, grids of 349–717 poses), 27 of the 48 unsure predictions' best poses were the true
grid pose, a drawn one 1 in ~500. The search's own done test then decides from the rendered
view, and an answer the search finds ambiguous is never confirmed: the start changes where the
search looks first, not what it accepts. Measured with ``cosmos bench --random-scenes R --n N
--onboard none --starts predicted`` (seed 23 at R = N = 3, seeds 5 and 11 at R = N = 2: 102
searches, with the matching fixes made alongside): searches ending after one render 58 → 77,
mean renders 5.3 → 3.8, found 94 → 96, none confirmed wrong before or after. Only without a pose
(no detection pairs with an object), when the optimizer refuses the request (an optimizer
without the route, a scene it does not know) or answers something unreadable does the search
start as it would without the prediction: at the start pose drawn from its seed at submission.
A given start keeps the paper's protocol exactly: nothing is predicted.
"""

from __future__ import annotations

import logging

from pydantic import ValidationError

from services.common.contracts.detect import DetectResponse
from services.common.contracts.optimize import GridPose, TargetImage
from services.common.contracts.start_pose import StartPoseRequest, StartPoseResponse
from services.common.images import media_type_of
from services.common.scene_models import object_classes
from services.controller.outages import OutagePolicy
from services.controller.progress import Progress
from services.controller.stages import StageError, Stages

__all__ = ["StartPicker", "predicts_start"]

_log = logging.getLogger("cosmos.controller")


def predicts_start(progress: Progress) -> bool:
    """Whether the search's first view waits for a predicted start: a new search (nothing
    recorded) submitted without a start pose."""
    return not progress.history and not progress.search.start_given


def start_request(progress: Progress) -> StartPoseRequest | None:
    """The optimizer's question for ``progress``'s target, with the scene's object classes when
    its own detector saw the target; None without target detections."""
    search, target = progress.search, progress.target
    if not target:
        return None
    own = progress.target_model is not None and progress.target_model.scene == search.scene
    return StartPoseRequest(
        scene=search.scene,
        target=TargetImage(image_size=progress.target_size, detections=target),
        **({"object_classes": object_classes(progress.scene.spec)} if own else {}),
    )


class StartPicker:
    """Picks a new search's first pose from its target (module docstring), through the stages
    and the outage policy the search loop uses."""

    def __init__(self, stages: Stages, outages: OutagePolicy) -> None:
        self.stages = stages
        self.outages = outages

    async def first_pose(self, progress: Progress, image: bytes) -> GridPose:
        """The predicted start of ``progress``'s search, else its drawn start; the target
        ``image`` is detected first (its detections go to ``progress``, recorded with the first
        iteration). Raises :class:`~.failures.SearchFailed` when a stage stays away."""
        search = progress.search
        if progress.target is None:
            seen: DetectResponse = await self.outages.call(
                search.id,
                lambda: self.stages.detect(
                    image, media_type_of(image), search.id, scene=search.scene
                ),
            )
            progress.saw_target(seen)
        request = start_request(progress)
        if request is None:
            return search.start
        answer = await self.outages.call(search.id, lambda: self._ask(request, search.id))
        if answer is None or answer.pose is None:
            why = "the optimizer gave no answer" if answer is None else answer.reason
            _log.info("search %s starts at its drawn pose: %s", search.id, why)
            return search.start
        if answer.status != "found":
            _log.info("search %s starts at the likeliest pose: %s", search.id, answer.reason)
        if not progress.grid.grid().contains(answer.pose.index):
            _log.warning("search %s: predicted start %s is off its grid", search.id, answer.pose)
            return search.start
        return answer.pose

    async def _ask(self, request: StartPoseRequest, search_id: str) -> StartPoseResponse | None:
        """The optimizer's prediction; None when it refuses or answers something unreadable
        (the search then starts without it). An outage is the policy's to ride out."""
        try:
            return await self.stages.start_pose(request, search_id)
        except StageError as exc:
            _log.warning("search %s: the optimizer refused a start pose: %s", search_id, exc)
        except ValidationError as exc:
            _log.warning("search %s: unreadable start pose answer: %s", search_id, exc)
        return None
