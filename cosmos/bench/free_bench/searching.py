"""One free target searched through the stack, and the floor it is measured against.

The search is a real ``POST /searches`` with ``mode=free`` (and ``fov_deg`` when the target
gives its intrinsics), followed to its ``end`` event (:func:`cosmos.bench.runner.
post_and_follow`): its wall time is what a client waits for.

Right after it, through the same services and the same connection pool, the bench times the
work a one-render search cannot avoid: ``POST /detect`` of the target on a detector, ``POST
/render`` of the search's first view (its camera, film and samples, as the controller asked
for it, PPM) on a renderer, and ``POST /detect`` of that view. Their sum is the *floor*; the
report's wall-time ratio is median wall ÷ median floor (issue 23's goal: ≤ 1.2).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import aiohttp

from cosmos.bench.free_bench.baseline import baseline_of_detections
from cosmos.bench.free_bench.records import (
    ANSWER,
    BASELINE,
    BOUND,
    BOXES,
    CameraRecord,
    FreeRecord,
    Outcome,
    camera_of,
    camera_record,
)
from cosmos.bench.free_bench.targets import VariantImage
from cosmos.bench.free_targets.draw import FreeTarget
from cosmos.bench.free_targets.estimate import Estimate, fov_of_focal
from cosmos.bench.runner import SearchRefused, post_and_follow
from services.common.auth import bearer
from services.common.contracts.detect import Detection
from services.common.contracts.free import DenseReport
from services.common.images import PPM_MEDIA_TYPE, media_type_of
from services.optimizer.free import SceneObjects

__all__ = ["StackCalls", "search_target"]


@dataclass(frozen=True)
class StackCalls:
    """Where the bench sends its calls: the controller (with its key), one renderer and one
    detector of the same stack (with the service token)."""

    controller: str
    renderer: str
    detector: str
    api_key: str | None
    service_token: str | None
    max_iterations: int


def _dense(result: Mapping[str, Any]) -> DenseReport | None:
    """The answer's dense refinement report, when one was made."""
    dense = (result.get("free") or {}).get("dense")
    return DenseReport.model_validate(dense) if dense else None


def _query(scene: str, target: FreeTarget, max_iterations: int) -> dict[str, str]:
    query = {"scene": scene, "mode": "free", "max_iterations": str(max_iterations)}
    if target.intrinsics_given:
        query["fov_deg"] = repr(target.annotations.camera.fov_deg)
    return query


def _outcome(raw: Mapping[str, Any]) -> Outcome:
    result = raw.get("result") or {}
    free = result.get("free") or {}
    succeeded = raw.get("status") == "succeeded"
    if succeeded and result.get("confirmed") and free.get("status") == "found":
        return "found"
    return "ambiguous" if free.get("pose") else "failed"


def _answer(raw: Mapping[str, Any]) -> tuple[CameraRecord | None, str | None]:
    pose = ((raw.get("result") or {}).get("free") or {}).get("pose")
    if not pose:
        return None, None
    camera = CameraRecord.model_validate(
        {
            "position": pose["position"],
            "quaternion_wxyz": pose["quaternion_wxyz"],
            "fov_deg": pose["intrinsics"]["fov_deg"],
        }
    )
    return camera, str(pose["intrinsics"]["source"])


def _first_view(raw: Mapping[str, Any]) -> tuple[dict[str, Any], tuple[int, int]] | None:
    """The camera (JSON) and film the search rendered first, when it rendered one: the first
    iteration's, or its candidate's own when it shows the render at that one's dense fit."""
    iterations = raw.get("iterations") or ()
    if not iterations or not iterations[0].get("camera"):
        return None
    width, height = iterations[0]["image_size"]
    first = iterations[0].get("candidate_camera") or iterations[0]["camera"]
    return first, (int(width), int(height))


def _boxes_pose(view: tuple[dict[str, Any], tuple[int, int]] | None) -> CameraRecord | None:
    """The first view's camera: the search's estimate from the boxes, before any render."""
    if view is None:
        return None
    camera, (width, _) = view
    return CameraRecord.model_validate(
        {
            "position": camera["position"],
            "quaternion_wxyz": camera["quaternion_wxyz"],
            "fov_deg": fov_of_focal(float(camera["fx_px"]), width),
        }
    )


async def _timed_post(
    http: aiohttp.ClientSession, url: str, data: bytes, headers: dict[str, str]
) -> tuple[bytes, str, float]:
    started = time.perf_counter()
    async with http.post(url, data=data, headers=headers) as response:
        body = await response.read()
        response.raise_for_status()
        kind = response.headers.get("Content-Type", "application/octet-stream")
    return body, kind.split(";")[0], (time.perf_counter() - started) * 1000


async def _floor(
    http: aiohttp.ClientSession,
    calls: StackCalls,
    scene: str,
    image: bytes,
    raw: Mapping[str, Any],
) -> tuple[float, float, float] | None:
    """Detect the target, render the search's first view, detect it (ms each; module
    docstring); None when the search rendered no view."""
    view = _first_view(raw)
    if view is None:
        return None
    camera, (width, height) = view
    token = bearer(calls.service_token)
    detect = f"{calls.detector}/detect?scene={scene}"
    _, _, detect_ms = await _timed_post(
        http, detect, image, {"Content-Type": media_type_of(image), **token}
    )
    body: dict[str, Any] = {"scene": scene, "camera": camera, "width": width, "height": height}
    spp = (raw.get("view_settings") or {}).get("spp")
    if spp is not None:
        body["spp"] = spp
    headers = {"Content-Type": "application/json", "Accept": f"{PPM_MEDIA_TYPE}, image/png;q=0.5"}
    rendered, kind, render_ms = await _timed_post(
        http, f"{calls.renderer}/render", json.dumps(body).encode(), {**headers, **token}
    )
    _, _, view_ms = await _timed_post(http, detect, rendered, {"Content-Type": kind, **token})
    return detect_ms, render_ms, view_ms


async def search_target(
    http: aiohttp.ClientSession,
    calls: StackCalls,
    target: FreeTarget,
    image: VariantImage,
    *,
    objects: SceneObjects,
    bound: Estimate,
    random: bool,
    onboarded: bool = False,
) -> FreeRecord:
    """Search ``image`` of ``target`` through the stack, time its floor, run the baseline on
    the search's detections; the record (``bound``: the target's box-only bound; ``random``
    a generated scene, ``onboarded`` once it has its own model)."""
    film = target.annotations.camera
    truth = Estimate.of_camera(target.camera, film.fov_deg, film.width)
    common: dict[str, Any] = {
        "scene": target.scene,
        "random": random,
        "onboarded": onboarded,
        "variant": image.variant,
        "index": target.index,
        "band": target.band,
        "elevation_deg": target.drawn.elevation_deg,
        "intrinsics_given": target.intrinsics_given,
        "objects": len(target.usable),
        "radius": objects.radius,
        "change": image.change,
        "truth": camera_of(truth),
        "fov_factor": film.fov_deg / objects.fov_deg,
        "roll_deg": target.camera.roll_deg,
    }
    started = time.perf_counter()
    try:
        raw, wall_ms = await post_and_follow(
            http, calls.controller, image.image, _query(target.scene, target, calls.max_iterations)
        )
    except (SearchRefused, aiohttp.ClientError, TimeoutError) as exc:
        return FreeRecord(
            **common,
            status="error",
            outcome="error",
            reason=str(exc) if isinstance(exc, SearchRefused) else f"{type(exc).__name__}: {exc}",
            wall_ms=(time.perf_counter() - started) * 1000,
            poses={ANSWER: None, BOXES: None, BASELINE: None, BOUND: camera_record(bound)},
        )
    floor = await _floor(http, calls, target.scene, image.image, raw)
    answer, source = _answer(raw)
    result = raw.get("result") or {}
    detections = raw.get("target_detections") or []
    size = tuple(raw.get("target_size") or (film.width, film.height))
    fov = film.fov_deg if target.intrinsics_given else objects.fov_deg
    baseline = baseline_of_detections(objects, detections, (int(size[0]), int(size[1])), fov)
    error = raw.get("error") or {}
    timings = [it.get("timings") or {} for it in raw.get("iterations") or ()]
    timings.append(result.get("refit_timings") or {})  # a render after the iterations, if any
    return FreeRecord(
        **common,
        search_id=raw.get("id"),
        status=str(raw.get("status")),
        outcome=_outcome(raw),
        reason=str(result.get("reason") or error.get("detail") or ""),
        steps=tuple(str(it.get("reason") or "") for it in raw.get("iterations") or ()),
        intrinsics_source=source,
        detections=len(detections),
        target_detections=tuple(Detection.model_validate(d) for d in detections),
        target_size=(int(size[0]), int(size[1])),
        renders=int(result.get("renders", len(raw.get("iterations") or ()))),
        wall_ms=wall_ms,
        render_ms=sum(t.get("render_ms", 0.0) for t in timings),
        detect_ms=sum(t.get("detect_ms", 0.0) for t in timings),
        optimize_ms=sum(t.get("optimize_ms", 0.0) for t in timings),
        refine_ms=sum(t.get("refine_ms", 0.0) for t in timings),
        floor_detect_ms=floor[0] if floor else None,
        floor_render_ms=floor[1] if floor else None,
        floor_view_detect_ms=floor[2] if floor else None,
        poses={
            ANSWER: answer,
            BOXES: _boxes_pose(_first_view(raw)),
            BASELINE: camera_record(baseline),
            BOUND: camera_record(bound),
        },
        dense=_dense(result),
    )
