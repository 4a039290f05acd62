"""The free search: any camera's pose from the target's boxes, confirmed by rendering it.

1. detect the target's objects (once; a resumed search reuses those it recorded);
2. ask the optimizer for the pose from the boxes alone (``POST /free-pose``): the best pose and,
   when it is ``ambiguous``, its alternatives; ``failed`` (no usable detection) fails the
   search with the optimizer's reason;
3. render the scene at the pose (a free camera with the intrinsics used, through the broker),
   on the target's shape at most the search's view width wide and the target's own (twice
   both without the photo's intrinsics: :data:`FOCAL_VIEW_SCALE`), and detect its objects;
4. compare them with the target's box by box (:mod:`~services.controller.free_match`) and,
   while the detector works, refine the pose densely against the target image by the same
   render (it came with its depth; :mod:`~services.controller.free_refine`). The render
   agrees when its boxes do and its edges do not contradict them (``edges_contradict``: a
   moved object can let a wrong pose pair every box), or when its edges agree
   (``edges_agree``: the fit was accepted and leaves most of the render's edges on the
   target's): a detector that names the render's objects unlike the target's (the general
   model on a scene it was not trained on) then still confirms a pose the image vouches for.
   If the render agrees, the search ends. If not, but the fit from it was accepted (or, too
   far to accept, is a ``lead``: the image vouches for where it ended), the pose it ended at
   is rendered and checked the same way (``worth_following``): the render says the candidate
   is not the target's pose, the fit found one near it. If that render agrees, it stands for
   the candidate and the search ends; if not, the next alternative is rendered, while renders
   remain (``max_iterations``, which these renders count too). A ``rivals`` answer (distinct
   poses explain the boxes almost as well), the intrinsics given, goes on after an agreeing
   render whose edges hold (:func:`~.free_refine.edges_hold`): its rivals are rendered too,
   for one render can tell its own pose from the target but not from a rival.

The answer (:class:`~services.common.contracts.free.FreeAnswer`, composed by
:mod:`~services.controller.free_verdict`) is ``found`` and ``confirmed`` only when the optimizer
found a unique pose and its render agreed; when the boxes pinned their one pose only loosely and
the render's edges pin it (the intrinsics given: :func:`~.free_refine.edges_pin`); or when, of a
``rivals`` answer's candidates, every one was rendered and only one agreed, and its edges hold.
Never with the focal length of the photo's EXIF, which no render can check: with one 15 % off,
14 of 16 answers of ``python -m benchmarks.exif_focal`` agreed with their render while 12-14 %
of the radius off; the render's edges overrule one that they pin elsewhere, and the answer then
takes their focal length (:mod:`~services.controller.exif_check`). Any other ambiguous pose
whose render agrees is answered ``ambiguous`` with its alternatives (the other agreeing ones
first), never confirmed; when no render agrees, the rendered pose that best explains the target
(the most edges on the target's after an accepted fit, then at its own render's pose, then the
box match) is answered, ``ambiguous`` and unconfirmed, saying so.

Every render is an iteration (its ``camera`` the free camera rendered, its ``pose`` the grid
pose nearest it), recorded as the hemisphere loop records its own (:class:`Writes`); the
optimizer's answer is a pure function of the target, so a resumed search asks again and goes on
with the candidate after its last recorded iteration.
"""

from __future__ import annotations

import asyncio
import time
from typing import Final, NoReturn

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.contracts.free import FreePose, FreePoseRequest, FreePoseResponse
from services.common.contracts.optimize import ImageDetections
from services.common.contracts.refine import MAX_FILM_SCALE, RefinePoseRequest, RefinePoseResponse
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import Iteration, Search, SearchResult, StageTimings
from services.common.depth_archive import DepthImage
from services.common.geometry.free_camera import FreeCamera
from services.common.images import encode_ppm, media_type_of
from services.controller import lens_check
from services.controller.events import Notifier
from services.controller.exif_check import exif_overruled, with_checked_focal
from services.controller.failures import SearchFailed, failure, unreadable_answer
from services.controller.free_candidates import as_rendered, with_candidate
from services.controller.free_iterations import (
    Seen,
    Step,
    iteration_of,
    render_agrees,
    spent,
    timed,
    timings_of,
    worth_following,
)
from services.controller.free_match import FreeMatch, compare_view, scaled_camera, view_film
from services.controller.free_refine import (
    alongside,
    ask_refinement,
    edges_hold,
    edges_pin,
    prepare_target,
    refine_by_render,
    refined_result,
    with_extra_renders,
)
from services.controller.free_verdict import (
    Verdict,
    checks_rivals,
    choice,
    free_result,
    others_standing,
)
from services.controller.outages import OutagePolicy
from services.controller.stages import Stages
from services.controller.store import Lease, SearchStore
from services.controller.writes import Writes

__all__ = ["FOCAL_VIEW_MAX_WIDTH", "FOCAL_VIEW_SCALE", "FreeSearchLoop"]

FOCAL_VIEW_SCALE: Final = 2
"""A search without the photo's intrinsics renders its views, and fits its focal length, on a
film this many times the view width (up to twice the photo's own size: below). The focal
length is told from the distance by the perspective of the edges, a pixel-scale effect at steep
views: ``python -m benchmarks.focal_valley --scale 2`` took the fits within 2 % of the true fov
from 29 % to 79 % at 60–89° (71 % to 95 % at 30–60°; nadir views stay flat). Through the stack, 24
drone-sized photos (4000 x 3000) of the demo without intrinsics (``python -m
benchmarks.drone_photos``, one run, views at 320 against 640): within 5 %/2° 16 → 23, median fov
error 2.2 % → 0.6 %, median search 616 → 1022 ms. A photo given with its intrinsics keeps the
view width.

A photo smaller than that film is rendered at up to twice its own size all the same
(:data:`~services.common.contracts.refine.MAX_FILM_SCALE`): the optimizer enlarges its grey to
the film, whose edges then fall between the photo's pixels, and fits with its tolerances in the
photo's pixels (:func:`~services.optimizer.free.dense.pyramid`). Through the stack (``cosmos
bench --free --scene demo --random-scenes 2 --n 8``, held-out seeds 21-23, 135 searches without
the fov on 320-480-pixel targets, one run each way): within 5 %/2° 51 → 67 (the scene's own
detector 18 → 31 of 45), median fov error 4.9 % → 3.6 % (own detector 4.4 % → 1.7 %), every
search given its fov unchanged, none confirmed wrong; 785 → 793 renders in all 360. The median
search without the fov took twice as long (seed 21, one run after the other: 930 → 1896 ms with
the own detector)."""
FOCAL_VIEW_MAX_WIDTH: Final = 1280
"""…but never wider than this (unless the view width itself is): the renderer's default limits
(2048 a side, 4.2 megapixels) take it on any shape up to 5:3 and 4:3 alike, and a fit of the
focal length there takes about four times one at 640."""


class FreeSearchLoop:
    """Runs one free search to its end over the stages (through the outage policy), recording
    it in the store and waking its followers."""

    def __init__(
        self, store: SearchStore, stages: Stages, notifier: Notifier, outages: OutagePolicy
    ) -> None:
        self.store = store
        self.stages = stages
        self.notifier = notifier
        self.outages = outages

    async def run(self, search: Search, image: bytes, lease: Lease | None = None) -> SearchResult:
        """Run a free search to its result, recording every render (under ``lease``, when
        several controllers share the database); raises
        :class:`~services.controller.failures.SearchFailed`, and
        :class:`~services.controller.store.LeaseLost` once another controller holds it."""
        writes = Writes(self.store, self.notifier, search, lease)
        try:
            return await self._solve(search, image, writes)
        finally:
            await writes.flush()

    async def _detect(self, search: Search, image: bytes) -> DetectResponse:
        sid = search.id
        return await self.outages.call(
            sid, lambda: self.stages.detect(image, media_type_of(image), sid, scene=search.scene)
        )

    async def _target(
        self, search: Search, image: bytes
    ) -> tuple[tuple[Detection, ...], tuple[int, int], DetectResponse | None]:
        """The target's detections and size: recorded, or detected now (then also returned, to
        be recorded with the first iteration)."""
        if search.target_detections is not None:
            return search.target_detections, search.target_size, None
        seen = await self._detect(search, image)
        return seen.detections, seen.image_size, seen

    async def _ask(
        self,
        search: Search,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        model: ModelInfo | None,
    ) -> tuple[FreePoseResponse, float]:
        """The optimizer's pose from the target's boxes (found by the detector ``model``), and
        its milliseconds."""
        detections, size = target
        request = FreePoseRequest(
            scene=search.scene,
            target=ImageDetections(image_size=size, detections=detections),
            intrinsics=search.intrinsics,
            detector_input=model.input_size if model is not None else None,
            attitude=search.attitude,
        )
        t0 = time.perf_counter()
        try:
            answer = await self.outages.call(
                search.id, lambda: self.stages.free_pose(request, search.id)
            )
        except ValidationError as exc:
            raise unreadable_answer(exc) from exc
        return answer, (time.perf_counter() - t0) * 1000

    async def _fail_without_pose(
        self, writes: Writes, seen: DetectResponse | None, detail: str, slug: str
    ) -> NoReturn:
        if seen is not None:
            await writes.update(target_detections=seen.detections, target_model=seen.model)
        title = "Nothing to search for" if slug == "no-target-objects" else "No camera pose"
        raise failure(slug, title, detail, status=422)

    async def _solve(self, search: Search, image: bytes, writes: Writes) -> SearchResult:
        sid = search.id
        scene = await self.outages.call(sid, lambda: self.stages.scene(search.scene, sid))
        target, size, seen = await self._target(search, image)
        if not target:
            detail = (
                "the detector found no objects in the target image: a photo showing some of "
                "the scene's objects (at least 3 for a pose, 4 without intrinsics)"
            )
            await self._fail_without_pose(writes, seen, detail, "no-target-objects")
        model = seen.model if seen is not None else search.target_model
        answer, optimize_ms = await self._ask(search, (target, size), model)
        if answer.pose is None:
            await self._fail_without_pose(writes, seen, answer.reason, "no-free-pose")
        # The optimizer makes the target ready for the refinements while the first view is
        # rendered (unless an older run finished the renders).
        done = bool(search.iterations) and search.iterations[-1].done
        film, _ = self._film(search, scene, size)
        ready = None if done else prepare_target(self.stages, search, image, film)
        async with alongside(ready):
            return await self._search(
                search, image, writes, scene, (target, size, seen), answer, optimize_ms
            )

    async def _search(
        self,
        search: Search,
        image: bytes,
        writes: Writes,
        scene: SceneDetail,
        detected: tuple[tuple[Detection, ...], tuple[int, int], DetectResponse | None],
        answer: FreePoseResponse,
        optimize_ms: float,
    ) -> SearchResult:
        """The search from the target's ``detected`` objects (its detections, its size and the
        detector's answer when it was detected now) and the optimizer's ``answer`` from their
        boxes (in ``optimize_ms``): the renders and the answer."""
        target, size, seen = detected
        grid = scene.spec.search.grid()
        history = list(search.iterations)
        answer = as_rendered(answer, history, size)
        candidates = answer.candidates
        if history and history[-1].done:  # finished by an older run, no result recorded
            chosen, agreed = choice(history, {})
            result = free_result(answer, history, grid, chosen, Verdict(agreed))
            result = refined_result(result, "no dense refinement (resumed after its render)", grid)
            return await writes.succeed(lens_check.lens_unchecked(result, search.intrinsics, grid))
        budget = min(len(candidates), search.max_iterations)
        rivals = checks_rivals(answer, search.intrinsics)
        edges: dict[int, RefinePoseResponse | str] = {}
        by_box: dict[int, bool] = {}
        followed = 0  # renders at candidates' dense fits: no iterations of their own
        for k in range(len(history), budget):
            if len(history) + followed >= search.max_iterations:
                break
            await writes.flush()
            pose = candidates[k]
            seen_view, outcome = await self._render_and_check(
                search, scene, (target, size), image, pose
            )
            spare = len(history) + followed + 1 < search.max_iterations
            follows: FreeCamera | None = None
            if spare and worth_following(seen_view.check, outcome):
                assert isinstance(outcome, RefinePoseResponse)
                followed += 1
                pose, seen_view, outcome, follows = await self._follow(
                    search, scene, (target, size), image, (pose, seen_view, outcome)
                )
                # the render that stands for the candidate was made at its fit: so is its pose
                answer = with_candidate(answer, k, pose)
            edges[k], by_box[k] = outcome, seen_view.check.agree
            # Its rivals are worth rendering only if this render's fit could be confirmed.
            goes_on = rivals and edges_hold(outcome, search.intrinsics) is not None
            ambiguous = answer.status != "found"
            step = Step(k, len(candidates), ambiguous, optimize_ms, goes_on, follows)
            following = candidates[k + 1] if k + 1 < budget else None
            iteration = iteration_of(step, pose, following, seen_view, grid, outcome)
            optimize_ms = 0.0
            history.append(iteration)
            writes.hold(iteration, seen)
            seen = None
            if iteration.done:
                break
        await writes.flush()
        result = await self._answer(
            search, scene, (target, size), image, answer, history, (edges, by_box), followed
        )
        return await writes.succeed(result)

    async def _follow(
        self,
        search: Search,
        scene: SceneDetail,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        image: bytes,
        first: tuple[FreePose, Seen, RefinePoseResponse],
    ) -> tuple[FreePose, Seen, RefinePoseResponse | str, FreeCamera | None]:
        """A candidate whose ``first`` render (its pose, what it showed, its accepted or
        leading fit) disagreed, rendered again at its fit
        (:func:`~.free_iterations.worth_following`): the pose, render and fit the candidate's
        iteration shows (the fit's when its render agrees, else the first's, the time of both
        in it), and the first render's camera when they are the fit's."""
        pose, seen, outcome = first
        again, refit = await self._render_and_check(search, scene, target, image, outcome.pose)
        if render_agrees(again.check, refit):
            return outcome.pose, spent(again, seen), refit, seen.camera
        return pose, spent(seen, again), outcome, None

    async def _answer(
        self,
        search: Search,
        scene: SceneDetail,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        image: bytes,
        answer: FreePoseResponse,
        history: list[Iteration],
        renders: tuple[dict[int, RefinePoseResponse | str], dict[int, bool]],
        followed: int,
    ) -> SearchResult:
        """The answer once the renders are done: the chosen candidate (:func:`_choice`), its
        fit refitted by one more render when it asks for one, and what the renders said
        (``renders``: each candidate's fit and whether its boxes agreed; ``followed``: the
        renders at dense fits, counted in the answer's renders)."""
        edges, by_box = renders
        grid = scene.spec.search.grid()
        chosen, agreed = choice(history, edges)
        outcome: RefinePoseResponse | str | None = edges.get(chosen.index)
        refit = None
        if agreed and outcome is not None:
            rendered = len(history) + followed
            outcome, extra = await self._refit(search, scene, target, image, outcome, rendered)
            refit = timings_of(extra) if extra is not None else None
        elif agreed:
            outcome = "no dense refinement (resumed after its render)"
        candidates = answer.candidates
        radius = scene.spec.camera.radius
        standing = others_standing(history, chosen, candidates, edges, radius) if agreed else ()
        ruled_out = (
            checks_rivals(answer, search.intrinsics)
            and agreed
            and len(history) == len(candidates)
            and not standing
        )
        known = search.intrinsics
        pinned = (
            edges_hold(outcome, known) if ruled_out else edges_pin(outcome, known, answer.ambiguity)
        )
        by_edges = agreed and not by_box.get(chosen.index, True)
        verdict = Verdict(agreed, by_edges, pinned if agreed else None, ruled_out, standing)
        result = free_result(answer, history, grid, chosen, verdict)
        if outcome is not None:
            result = refined_result(result, outcome, grid)
        overruled = exif_overruled(outcome)
        if overruled is not None and isinstance(outcome, RefinePoseResponse):
            stated = outcome.pose.intrinsics.fx_px
            result = with_checked_focal(result, overruled, stated, grid)
        bent, lens = lens_check.lens_bent(outcome), None
        if bent is not None:
            spare = len(history) + followed + (refit is not None) < search.max_iterations
            if bent.lens_pose is not None and spare:
                bent, lens = await self._through_lens(search, scene, target[1], image, bent)
            result = lens_check.with_lens_doubt(result, bent, grid)
        return with_extra_renders(result, refit, followed, lens)

    async def _through_lens(
        self,
        search: Search,
        scene: SceneDetail,
        size: tuple[int, int],
        image: bytes,
        bent: RefinePoseResponse,
    ) -> tuple[RefinePoseResponse, StageTimings | None]:
        """:func:`~.lens_check.refit_through_lens` by this search's stages."""

        async def render(pose: FreePose) -> tuple[bytes, float]:
            _, archive, _, render_ms = await self._render(search, scene, size, pose)
            return archive, render_ms

        async def refine(request: RefinePoseRequest, archive: bytes) -> RefinePoseResponse | str:
            stages, outages, sid = self.stages, self.outages, search.id
            return await ask_refinement(stages, outages, sid, request, image, archive)

        return await lens_check.refit_through_lens(bent, search, render, refine)

    async def _refit(
        self,
        search: Search,
        scene: SceneDetail,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        image: bytes,
        outcome: RefinePoseResponse | str,
        rendered: int,
    ) -> tuple[RefinePoseResponse | str, Seen | None]:
        """One render more at an accepted fit that asks for it (``render_again``: the focal
        length fitted far from the render), within ``max_iterations``, and the refit from there,
        kept when accepted: the outcome and the render added, if any (none when it failed: a
        retry would resume after the iterations, without any fit)."""
        if isinstance(outcome, str) or not outcome.fit.render_again:
            return outcome, None
        if rendered >= search.max_iterations:
            return outcome, None
        try:
            seen, again = await self._render_and_check(search, scene, target, image, outcome.pose)
        except SearchFailed:
            return outcome, None
        if isinstance(again, str) or not again.fit.accepted:
            return outcome, seen
        return again, seen

    async def _render_and_check(
        self,
        search: Search,
        scene: SceneDetail,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        image: bytes,
        pose: FreePose,
    ) -> tuple[Seen, RefinePoseResponse | str]:
        """``pose`` rendered, then at once detected and compared with the ``target`` (its
        detections and size) and refined densely against its ``image`` by that render (neither
        needs the other: the refinement takes the render's own depth, not its detections)."""
        camera, archive, colours, render_ms = await self._render(search, scene, target[1], pose)
        refined = asyncio.create_task(
            timed(refine_by_render(self.stages, self.outages, search, image, pose, archive))
        )
        try:
            found, check, detect_ms = await self._compare(search, target, pose, colours)
        except BaseException:
            refined.cancel()  # the search fails (or is cancelled) as it would have without it
            raise
        outcome, refine_ms = await refined
        return Seen(camera, archive, found, check, render_ms, detect_ms, refine_ms), outcome

    def _film(
        self, search: Search, scene: SceneDetail, size: tuple[int, int]
    ) -> tuple[tuple[int, int], float]:
        """The renders' film for a target of ``size`` (:func:`~.free_match.view_film`, at most
        the search's view width and the target's own; without the photo's intrinsics
        :data:`FOCAL_VIEW_SCALE` times both, up to :data:`FOCAL_VIEW_MAX_WIDTH`) and the scale
        from target to film."""
        settings = self.stages.settings_for(search.view_settings)
        width = settings.width or scene.spec.camera.width
        if search.intrinsics is None:
            width = max(width, min(FOCAL_VIEW_SCALE * width, FOCAL_VIEW_MAX_WIDTH))
            return view_film(size, width, max_scale=MAX_FILM_SCALE)
        return view_film(size, width)

    async def _render(
        self, search: Search, scene: SceneDetail, size: tuple[int, int], pose: FreePose
    ) -> tuple[FreeCamera, bytes, NDArray[np.uint8], float]:
        """``pose`` rendered on the target's shape (``size``) at most the view width wide, with
        its depth: the camera rendered, the archive, its colours and the milliseconds."""
        sid = search.id
        settings = self.stages.settings_for(search.view_settings)
        film, scale = self._film(search, scene, size)
        camera = scaled_camera(pose, scale)
        started = time.perf_counter()
        archive = await self.outages.call(
            sid,
            lambda: self.stages.render_camera(
                search.scene, camera, film, sid, settings, with_depth=True
            ),
        )
        try:
            colours = DepthImage.from_npz(archive).rgb
        except ValueError as exc:
            raise failure("bad-render", "Bad render", f"the renderer's archive: {exc}") from exc
        if colours is None:
            raise failure("bad-render", "Bad render", "the renderer's archive has no colours")
        return camera, archive, colours, (time.perf_counter() - started) * 1000

    async def _compare(
        self,
        search: Search,
        target: tuple[tuple[Detection, ...], tuple[int, int]],
        pose: FreePose,
        colours: NDArray[np.uint8],
    ) -> tuple[DetectResponse, FreeMatch, float]:
        """The render's ``colours`` detected and compared box by box with the ``target``'s
        detections of ``pose``'s pairs; the milliseconds the detection took."""
        detections, size = target
        started = time.perf_counter()
        found = await self._detect(search, encode_ppm(colours))
        detect_ms = (time.perf_counter() - started) * 1000
        paired = [c.detection for c in pose.correspondences]
        names = [c.object for c in pose.correspondences]
        check = compare_view(detections, size, paired, found.detections, found.image_size, names)
        return found, check, detect_ms
