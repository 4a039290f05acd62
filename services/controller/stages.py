"""The stage calls a search makes, each through the broker: render (a grid pose, or a free
camera, with its depth when asked), detect, optimize (the next pose, the free pose from the
target's boxes and its dense refinement by a render, or a hemisphere search's predicted start
pose).

Every call forwards the search's request id (``X-Request-ID``). A 4xx answer from a stage is a
:class:`StageError` carrying that stage's problem details (the search fails with it); transport
failures and 5xx answers are the broker's to retry elsewhere.

Views are rendered with a search's own :class:`ViewSettings` (samples per pixel, film width),
recorded when it was submitted; ``view_settings=None`` (a search stored by an earlier version,
or a view of no search) means the controller's current ones, :attr:`Stages.view_settings`.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from typing import Any
from urllib.parse import urlencode

from services.common.contracts.detect import DetectResponse
from services.common.contracts.free import FreePoseRequest, FreePoseResponse
from services.common.contracts.optimize import NextPoseRequest, NextPoseResponse
from services.common.contracts.refine import (
    RefinePoseRequest,
    RefinePoseResponse,
    TargetRequest,
    TargetResponse,
)
from services.common.contracts.render import SceneDetail
from services.common.contracts.search import ViewSettings
from services.common.contracts.start_pose import StartPoseRequest, StartPoseResponse
from services.common.depth_archive import DEPTH_MEDIA_TYPE
from services.common.errors import ProblemDetails
from services.common.geometry.free_camera import FreeCamera
from services.common.geometry.pose import GridIndex
from services.common.images import PPM_MEDIA_TYPE, media_type_of
from services.controller.broker import Broker
from services.controller.transport import StageAnswer, StageRequest

__all__ = ["StageError", "Stages", "request_json"]


def request_json(request: RefinePoseRequest) -> str:
    """A ``/refine-pose`` request's JSON: the fields the code set, a null among them. Its pose
    may be an alternative, whose σ is a required null: ``exclude_none`` (what the other stage
    calls send, as the optimizer refuses a null where its schema says "never null") left it
    out, and the optimizer refused the request as missing it."""
    return request.model_dump_json(exclude_unset=True)


class StageError(RuntimeError):
    """A stage refused a task (4xx); ``problem`` is its answer."""

    def __init__(self, stage: str, problem: ProblemDetails) -> None:
        super().__init__(f"{stage}: {problem.detail or problem.title}")
        self.stage = stage
        self.problem = problem


def _problem(stage: str, response: StageAnswer) -> StageError:
    try:
        body: Any = response.json()
        problem = ProblemDetails.model_validate(body)
    except ValueError:
        problem = ProblemDetails(
            title="Stage error", status=response.status_code, detail=response.text[:500]
        )
    return StageError(stage, problem)


class Stages:
    """Typed calls of the renderer, detector and optimizer through one broker."""

    def __init__(
        self, broker: Broker, *, render_spp: int | None = None, render_width: int | None = None
    ) -> None:
        self.broker = broker
        self.view_settings = ViewSettings(spp=render_spp, width=render_width)
        """The controller's current view settings: what a search submitted now records."""
        self._scenes: dict[str, SceneDetail] = {}
        self._early: dict[tuple[str, str, int, int, ViewSettings], asyncio.Task[bytes]] = {}
        self.on_render: Callable[[str, GridIndex, ViewSettings, bytes], None] | None = None
        """Told of every view rendered, with the settings it was rendered with (the page shows
        them: :mod:`services.controller.views`)."""

    def settings_for(self, view_settings: ViewSettings | None) -> ViewSettings:
        """The settings a view is rendered with: ``view_settings`` (a search's own), else the
        controller's current ones."""
        return self.view_settings if view_settings is None else view_settings

    async def scene(self, scene_id: str, request_id: str = "") -> SceneDetail:
        """The scene's spec and grid from a renderer (cached: scenes are static)."""
        if scene_id not in self._scenes:
            request = StageRequest(
                "GET", f"/scenes/{scene_id}", headers={"X-Request-ID": request_id}
            )
            response = await self._call("renderer", "scene", request)
            self._scenes[scene_id] = SceneDetail.model_validate_json(response.content)
        return self._scenes[scene_id]

    def render_early(
        self,
        scene_id: str,
        index: GridIndex,
        request_id: str,
        view_settings: ViewSettings | None = None,
    ) -> None:
        """Start rendering ``index`` now: the next :meth:`render` of it for ``request_id`` with
        the same settings gets this answer instead of asking again (a search's start view, while
        its submission is still being checked and stored). :meth:`forget_early` drops what is
        not taken."""
        settings = self.settings_for(view_settings)
        key = (request_id, scene_id, index.lat, index.lon, settings)
        if key not in self._early:
            self._early[key] = asyncio.create_task(
                self._render(scene_id, index, request_id, settings)
            )

    def forget_early(self, request_id: str) -> None:
        """Cancel and drop the early renders of ``request_id`` that nobody took."""
        for key in [key for key in self._early if key[0] == request_id]:
            # also marks a failure nobody will await as seen: asyncio does not report it
            self._early.pop(key).cancel()

    async def render(
        self,
        scene_id: str,
        index: GridIndex,
        request_id: str = "",
        view_settings: ViewSettings | None = None,
    ) -> bytes:
        """The scene seen from grid pose ``index`` with ``view_settings`` (None: the
        controller's current ones): binary PPM bytes (PNG from a renderer that does not offer
        PPM). The view only travels on to the detector, so it is not compressed. An early render
        of it (:meth:`render_early`) is awaited instead of a new one."""
        settings = self.settings_for(view_settings)
        early = self._early.pop((request_id, scene_id, index.lat, index.lon, settings), None)
        if early is not None:
            return await early
        return await self._render(scene_id, index, request_id, settings)

    async def _render(
        self, scene_id: str, index: GridIndex, request_id: str, settings: ViewSettings
    ) -> bytes:
        body: dict[str, Any] = {"scene": scene_id, "pose": index.model_dump()}
        if settings.spp is not None:
            body["spp"] = settings.spp
        if settings.width is not None:
            body["width"] = settings.width
        headers = {"X-Request-ID": request_id, "Accept": f"{PPM_MEDIA_TYPE}, image/png;q=0.5"}
        request = StageRequest.json("/render", json.dumps(body), headers)
        image = (await self._call("renderer", "render", request)).content
        if self.on_render is not None:
            self.on_render(scene_id, index, settings, image)
        return image

    async def render_camera(
        self,
        scene_id: str,
        camera: FreeCamera,
        size: tuple[int, int],
        request_id: str = "",
        view_settings: ViewSettings | None = None,
        *,
        with_depth: bool = False,
    ) -> bytes:
        """The scene seen from the free ``camera`` on a film of ``size`` (width, height; the
        camera's pixel intrinsics are in its pixels), sampled as ``view_settings`` say (their
        width is the caller's to apply): binary PPM bytes, or PNG, as :meth:`render`; with
        ``with_depth``, the renderer's archive of its colours, depth and object ids
        (:class:`~services.common.depth_archive.DepthImage`), from the same one call."""
        settings = self.settings_for(view_settings)
        body: dict[str, Any] = {
            "scene": scene_id,
            "camera": camera.model_dump(mode="json", exclude_none=True),
            "width": size[0],
            "height": size[1],
        }
        if settings.spp is not None:
            body["spp"] = settings.spp
        accept = DEPTH_MEDIA_TYPE if with_depth else f"{PPM_MEDIA_TYPE}, image/png;q=0.5"
        headers = {"X-Request-ID": request_id, "Accept": accept}
        request = StageRequest.json("/render", json.dumps(body), headers)
        answer = await self._call("renderer", "render", request)
        if with_depth and answer.headers.get("content-type") != DEPTH_MEDIA_TYPE:
            raise StageError(
                "renderer",
                ProblemDetails(
                    title="No depth", status=502, detail="the renderer gave no depth archive"
                ),
            )
        return answer.content

    async def detect(
        self, image: bytes, media_type: str, request_id: str = "", *, scene: str | None = None
    ) -> DetectResponse:
        """The objects found in an image, sent as the raw body (no multipart to write or parse:
        the detector takes ``image/png``, ``image/jpeg`` and binary PPM bodies as they are).
        ``scene`` (the search's) lets the detector use that scene's own model if it has one."""
        headers = {"X-Request-ID": request_id, "Content-Type": media_type}
        path = "/detect" if scene is None else f"/detect?{urlencode({'scene': scene})}"
        response = await self._call(
            "detector", "detect", StageRequest("POST", path, image, headers)
        )
        return DetectResponse.model_validate_json(response.content)

    async def optimize(self, request: NextPoseRequest, request_id: str = "") -> NextPoseResponse:
        """The optimizer's answer to ``POST /next-pose`` (a ValidationError if it is malformed)."""
        body = request.model_dump_json(exclude_none=True)
        call = StageRequest.json("/next-pose", body, {"X-Request-ID": request_id})
        response = await self._call("optimizer", "optimize", call)
        return NextPoseResponse.model_validate_json(response.content)

    async def start_pose(
        self, request: StartPoseRequest, request_id: str = ""
    ) -> StartPoseResponse:
        """The optimizer's answer to ``POST /start-pose`` (a ValidationError if malformed)."""
        body = request.model_dump_json(exclude_none=True)
        call = StageRequest.json("/start-pose", body, {"X-Request-ID": request_id})
        response = await self._call("optimizer", "start-pose", call)
        return StartPoseResponse.model_validate_json(response.content)

    async def free_pose(self, request: FreePoseRequest, request_id: str = "") -> FreePoseResponse:
        """The optimizer's answer to ``POST /free-pose`` (a ValidationError if it is malformed)."""
        body = request.model_dump_json(exclude_none=True)
        call = StageRequest.json("/free-pose", body, {"X-Request-ID": request_id})
        response = await self._call("optimizer", "solve", call)
        return FreePoseResponse.model_validate_json(response.content)

    async def refine_pose(
        self, request: RefinePoseRequest, target: bytes, render: bytes, request_id: str = ""
    ) -> RefinePoseResponse:
        """The optimizer's answer to ``POST /refine-pose``: ``request`` with the ``target``
        image and the ``render`` archive at its pose, one form (a ValidationError if the answer
        is malformed)."""
        parts = [
            ("request", "text/plain", request_json(request).encode()),
            ("target", media_type_of(target), target),
            ("render", DEPTH_MEDIA_TYPE, render),
        ]
        call = StageRequest.form("/refine-pose", parts, {"X-Request-ID": request_id})
        response = await self._call("optimizer", "refine", call, affinity=request_id or None)
        return RefinePoseResponse.model_validate_json(response.content)

    async def prepare_target(
        self, request: TargetRequest, target: bytes, request_id: str = ""
    ) -> TargetResponse:
        """The optimizer's answer to ``POST /refine-pose/target``: the ``target`` image made
        ready for the refinements on ``request``'s film (a ValidationError if the answer is
        malformed)."""
        parts = [
            ("request", "text/plain", request.model_dump_json().encode()),
            ("target", media_type_of(target), target),
        ]
        call = StageRequest.form("/refine-pose/target", parts, {"X-Request-ID": request_id})
        response = await self._call("optimizer", "target", call, affinity=request_id or None)
        return TargetResponse.model_validate_json(response.content)

    async def wait_for_replica(self, stage: str, timeout_s: float) -> bool:
        """Wait until a replica of ``stage`` answers again (see
        :meth:`Broker.wait_for_replica`); False if none did within ``timeout_s``."""
        return await self.broker.wait_for_replica(stage, timeout_s)

    async def _call(
        self, stage: str, kind: str, request: StageRequest, *, affinity: str | None = None
    ) -> StageAnswer:
        """``request`` through the broker (to the replica that served ``affinity`` last, when
        it is no busier); any answer but 200 is the stage's :class:`StageError`."""
        response = await self.broker.call(stage, kind, request, affinity)
        if response.status_code != 200:
            raise _problem(stage, response)
        return response
