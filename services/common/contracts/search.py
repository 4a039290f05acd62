"""Message models of a search (the controller's public API): status, iterations, result."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Final, Literal

from pydantic import ConfigDict, Field, Strict

from services.common.base import FrozenModel, Integer, Number
from services.common.contracts.detect import Detection, ModelInfo
from services.common.contracts.free import CameraAttitude, FreeAnswer, PhotoIntrinsics
from services.common.contracts.optimize import GridPose, StrategyName, ViewMatch
from services.common.errors import ProblemDetails, problem_type
from services.common.geometry.free_camera import FreeCamera
from services.common.geometry.pose import Pose

__all__ = [
    "MAX_ITERATIONS",
    "OUTAGE",
    "SEARCH_EVENTS",
    "ControllerHealth",
    "Iteration",
    "ReplicaHealth",
    "ReplicaState",
    "Search",
    "SearchMode",
    "SearchOptions",
    "SearchPage",
    "SearchResult",
    "SearchStatus",
    "StageTimings",
    "TERMINAL_STATUSES",
    "ViewSettings",
    "ViewSpp",
    "ViewWidth",
]

SearchStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
SearchMode = Literal["hemisphere", "free"]
"""``hemisphere``: the paper's search over the scene's grid of poses; ``free``: any camera,
solved from the target's boxes and confirmed by rendering it
(:mod:`services.controller.free_loop`)."""
TERMINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})

OUTAGE: Final = problem_type("stage-unavailable")
"""The ``type`` of a search's error when a stage was unavailable for longer than the controller
waits: the one failure ``POST /searches/{id}/retry`` resumes (the search keeps its image)."""


NonNegMs = Annotated[Number, Field(ge=0.0)]
Unit = Annotated[Number, Field(ge=0.0, le=1.0)]
Count = Annotated[Integer, Field(ge=0)]

MAX_ITERATIONS: Final = 500

_NUMBER = r"\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*"
_FOUR_NUMBERS = rf"^{_NUMBER},{_NUMBER},{_NUMBER},{_NUMBER}$"
"""Four comma-separated decimal numbers, as a form field carries a camera's four parameters."""
_LENS_NUMBERS = rf"^{_NUMBER},{_NUMBER},{_NUMBER},{_NUMBER}(,{_NUMBER})?$"
"""OpenCV's distortion coefficients ``k1,k2,p1,p2`` and optionally ``k3``."""
_TWO_NUMBERS = rf"^{_NUMBER},{_NUMBER}$"
"""Two comma-separated decimal numbers: a camera's pitch and roll."""

ViewSpp = Annotated[int, Field(ge=1, le=1024)]
"""Samples per pixel of a search's views (the controller's ``COSMOS_CONTROLLER_VIEW_SPP``)."""
ViewWidth = Annotated[int, Field(ge=8, le=8192)]
"""Film width of a search's views in pixels (``COSMOS_CONTROLLER_VIEW_WIDTH``); the height
follows the scene's aspect."""


class ViewSettings(FrozenModel):
    """How a search's views are rendered, besides its scene and pose (the seed is the
    renderer's fixed one): recorded when it is submitted, so that every view it renders, and
    every view of it rendered again later, is the same pixels whatever the controller's
    settings are by then. None: the renderer's default samples, the scene's own film width."""

    spp: Annotated[ViewSpp, Strict()] | None = Field(
        default=None, description="Samples per pixel (null: the renderer's default)."
    )
    width: Annotated[ViewWidth, Strict()] | None = Field(
        default=None, description="Film width in pixels (null: the scene's own)."
    )


class SearchOptions(FrozenModel):
    """What ``POST /searches`` takes besides the image: the form's text fields, or the query
    beside a raw image body. Unknown names are ignored, as for any form. The values are text,
    so numbers are read from it (not strict, unlike the JSON messages')."""

    model_config = ConfigDict(extra="ignore", frozen=True, allow_inf_nan=False)

    scene: Annotated[str, Field(min_length=1, max_length=128, description="The scene's id.")]
    strategy: StrategyName = Field(default="reprojection", description="The search strategy.")
    start_theta_deg: Annotated[float, Field(ge=0.0, le=90.0)] | None = Field(
        default=None, description="Start pose (snapped to the grid); with start_phi_deg."
    )
    start_phi_deg: float | None = Field(default=None, description="Start pose's longitude.")
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] | None = Field(
        default=None, description="Draws the start pose when none is given (recorded)."
    )
    max_iterations: Annotated[int, Field(ge=1, le=MAX_ITERATIONS)] | None = Field(
        default=None, description="Give up after this many views (default: the controller's)."
    )
    mode: SearchMode = Field(
        default="hemisphere",
        description="`hemisphere`: the paper's search over the scene's grid; `free`: any camera "
        "(position, orientation, intrinsics) from the target's boxes, confirmed by a render.",
    )
    fov_deg: Annotated[float, Field(gt=0.0, lt=180.0)] | None = Field(
        default=None, description="Free mode: the photo's horizontal field of view in degrees."
    )
    intrinsics: Annotated[str, Field(max_length=200, pattern=_FOUR_NUMBERS)] | None = Field(
        default=None,
        description="Free mode: the photo's OpenCV intrinsics `fx,fy,cx,cy` in its pixels "
        "(instead of fov_deg).",
    )
    distortion: Annotated[str, Field(max_length=250, pattern=_LENS_NUMBERS)] | None = Field(
        default=None,
        description="Free mode: the photo's OpenCV lens distortion `k1,k2,p1,p2` or "
        "`k1,k2,p1,p2,k3` (with fov_deg or intrinsics).",
    )
    attitude: Annotated[str, Field(max_length=100, pattern=_TWO_NUMBERS)] | None = Field(
        default=None,
        description="Free mode: the camera's `pitch,roll` in degrees, as a flight log states "
        "them (pitch below the horizontal, 90 straight down; roll turning the camera clockwise "
        "as seen from behind it): poses whose down direction lies more than 10° from theirs are "
        "not answered. Without it, a drone photo's XMP gimbal angles stand for it.",
    )
    exif: bool = Field(
        default=True,
        description="Free mode, without fov_deg and intrinsics: take the intrinsics from the "
        "photo's metadata, a drone's calibration in its XMP (DJI's DewarpData: focal lengths, "
        "principal point, distortion) or else the focal length its EXIF states "
        "(FocalLengthIn35mmFilm, or FocalLength with FocalPlaneXResolution); and the camera's "
        "pitch and roll its gimbal's angles in the XMP state. false reads none of them and "
        "estimates the focal length from the boxes instead.",
    )


class StageTimings(FrozenModel):
    """Where one iteration's time went, in milliseconds (wall time seen by the controller)."""

    render_ms: NonNegMs = 0.0
    detect_ms: NonNegMs = 0.0
    optimize_ms: NonNegMs = 0.0
    refine_ms: NonNegMs = Field(
        default=0.0,
        description="A dense refinement by the render (a free search's alongside the detection).",
    )
    total_ms: NonNegMs = 0.0


class Iteration(FrozenModel):
    """One rendered view of a search and what the optimizer made of it."""

    index: Count
    pose: GridPose
    image_size: tuple[Integer, Integer]
    detections: tuple[Detection, ...]
    timings: StageTimings
    estimate: Pose | None = Field(default=None, description="The continuous estimate so far.")
    estimate_grid: GridPose | None = Field(
        default=None, description="The grid pose nearest the estimate."
    )
    confidence: Unit = 0.0
    ambiguous: bool = False
    next_pose: GridPose | None = None
    done: bool = False
    agrees: bool | None = Field(
        default=None,
        description="A free search's view: its render agrees with the target (box by box, its "
        "edges not contradicting, or by its edges). It is not `done` when the search goes on to "
        "render the pose's rivals. Null for a grid view.",
    )
    reason: str = ""
    match: ViewMatch | None = Field(
        default=None, description="How well this view matches the target (optimizer's answer)."
    )
    detector_sha256: str | None = Field(
        default=None,
        description="The detector model that found this view's detections (its sha256).",
    )
    camera: FreeCamera | None = Field(
        default=None,
        description="A free search's view: the camera rendered, intrinsics in pixels of this "
        "view (`image_size`); `pose` is then the grid pose nearest it. Null for a grid view.",
    )
    candidate_camera: FreeCamera | None = Field(
        default=None,
        description="A free search's view rendered at a candidate's dense fit, the candidate's "
        "own render having disagreed with the target: the camera of that first render (on the "
        "same film). Null otherwise.",
    )


class SearchResult(FrozenModel):
    """Where the camera stood: the grid pose, the continuous estimate and how sure it is.

    ``confirmed`` is false for an any-time answer: no view was confirmed to match the target
    before the search ran out of iterations or went round in circles, so the result is the
    visited pose whose view matched best, its match score as ``confidence``, and ``reason``
    says why it is not confirmed. It is false too for an answer the search itself finds
    ``ambiguous`` (another pose explains the target about as well): a confirmed answer is one
    the search vouches for.
    """

    pose: GridPose
    refined_pose: Pose
    confidence: Unit
    renders: Count
    ambiguous: bool = False
    reason: str = ""
    confirmed: bool = Field(
        default=True,
        description="False when no view was confirmed to match the target (the pose is the "
        "best visited one, not a found one), or when the answer is ambiguous.",
    )
    free: FreeAnswer | None = Field(
        default=None,
        description="A free search's answer: the camera's position, orientation and "
        "intrinsics, the pairs, residual and alternatives; `pose` is then the grid pose nearest "
        "it and `refined_pose` its direction from the scene centre. Null for a hemisphere search.",
    )
    refit_timings: StageTimings | None = Field(
        default=None,
        description="Renders after the iterations: a free search's at the refined pose (a "
        "fit of the focal length that moved far from the render) and through the lens a lens "
        "check estimated, a hemisphere search's with depth at its unconfirmed answer (its "
        "edges settle it): their render, detect and dense refinement milliseconds, summed. "
        "Null when none was made.",
    )


class Search(FrozenModel):
    """``GET /searches/{id}``."""

    id: str
    status: SearchStatus
    scene: str
    strategy: StrategyName
    start: GridPose
    start_given: bool = Field(
        default=True,
        description="Whether the submission gave the start pose. A search without one takes its "
        "first view at the grid pose the optimizer predicts from the target's detections "
        "(`POST /start-pose`), and at `start` (drawn from `seed`) when it cannot predict one.",
    )
    seed: Integer
    max_iterations: Integer
    created_at: datetime
    updated_at: datetime
    target_size: tuple[Integer, Integer] = Field(
        description="Target image (width, height) in pixels."
    )
    target_detections: tuple[Detection, ...] | None = None
    target_model: ModelInfo | None = Field(
        default=None,
        description="The detector model that found the target's detections: the scene's own "
        "(``scene`` set) or the general one.",
    )
    iterations: tuple[Iteration, ...] = ()
    result: SearchResult | None = None
    error: ProblemDetails | None = None
    mode: SearchMode = Field(
        default="hemisphere",
        description="`free`: any camera from the target's boxes (`start` is not used).",
    )
    intrinsics: PhotoIntrinsics | None = Field(
        default=None, description="A free search's photo intrinsics, when they were given."
    )
    attitude: CameraAttitude | None = Field(
        default=None,
        description="A free search's camera pitch and roll, when its photo states them (a "
        "drone's gimbal, in its XMP): poses far from them are not answered.",
    )
    view_settings: ViewSettings | None = Field(
        default=None,
        description="How the search's views are rendered, recorded when it was submitted: its "
        "views, and any of them rendered again (`/searches/{id}/iterations/{n}/view.png`), use "
        "these whatever the controller's settings are later. Null for a search stored by an "
        "earlier version: the controller's current settings.",
    )


SEARCH_EVENTS: Final[dict[str, type[FrozenModel]]] = {
    "search": Search,
    "iteration": Iteration,
    "end": Search,
}
"""What each server-sent event of ``GET /searches/{id}/events`` carries as its data: ``search``,
the search without its iterations whenever it changed while queued or running (its status, its
target's detections); ``iteration``, each recorded iteration in order; ``end``, once, the
finished search without its iterations."""


class SearchPage(FrozenModel):
    """``GET /searches``: newest first."""

    items: tuple[Search, ...]
    total: Count
    limit: Count
    offset: Count


ReplicaState = Literal["up", "failing", "out"]
"""``up``; ``failing``: its last task or health probe failed, it still gets tasks; ``out``: it
failed repeatedly and gets none until it answers ``/health`` again."""


class ReplicaHealth(FrozenModel):
    """A stage replica as the controller's broker knows it, by name: its address is in the
    controller's log (``renderer-1 is http://…``), never in an answer."""

    name: str = Field(
        description="The stage and a number (`renderer-1`), given in the order the controller "
        "met the replicas; a replica keeps its name while the controller runs."
    )
    stage: str
    state: ReplicaState = Field(
        description="`up`; `failing`: its last task or health probe failed, it still gets "
        "tasks; `out`: it failed repeatedly and gets none until it answers again."
    )
    up: bool = Field(description="It gets tasks (`state` is not `out`).")
    in_flight: Count = Field(description="Tasks this controller has sent it that are running.")
    reported_load: Number = Field(description="Requests in flight, as its own /health says.")
    expected_ms: dict[str, Number] = Field(
        description="Per kind of task (`render`, `detect`, ...), the exponential moving average "
        "of its recent durations in ms: what placement uses."
    )
    served: Count
    failed: Count


class ControllerHealth(FrozenModel):
    """``GET /health`` of the controller: ``degraded`` while a stage has no replica available;
    the store's figures (whole-store, every tenant's) for an admin key only."""

    status: Literal["ok", "degraded"]
    service: Literal["controller"]
    searches_queued: Count
    searches_running: Count
    broker_heuristic: str
    replicas: tuple[ReplicaHealth, ...]
    store_searches: Count | None = Field(
        default=None,
        description="Searches held, every tenant's (finished ones expire). With an admin key "
        "only (or with keys off); null otherwise.",
    )
    store_image_bytes: Count | None = Field(
        default=None,
        description="Bytes of the target images held. With an admin key only; null otherwise.",
    )
    store_bytes: Count | None = Field(
        default=None,
        description="Bytes of the database's pages in use (free pages and the log aside). With "
        "an admin key only; null otherwise.",
    )
    unavailable_stages: tuple[str, ...] = Field(
        default=(),
        description="Stages no replica serves now: running searches wait for them (up to the "
        "controller's outage budget) and new submissions are refused with 503 and Retry-After.",
    )
