"""What ``cosmos bench --free`` keeps of one search: the target's truth, the answer's pose as the
controller gave it, the pose of its first render (the estimate from the boxes, before any
render), the two references on the same target, timings, and the errors of each, recomputed from
the poses whenever a table is made (never stored as figures).

Errors are :func:`cosmos.bench.free_targets.metrics.pose_error`'s: position ``|c − c*| / r`` (r
the scene's hemisphere radius), rotation the angle of ``R_estᵀ R_true``, fov ``|f − f*| / f*``.
"""

from __future__ import annotations

from typing import Final, Literal

import numpy as np

from cosmos.bench.free_targets.draw import FOV_RANGE
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import PoseError, pose_error
from services.common.base import FrozenModel
from services.common.contracts.detect import Detection
from services.common.contracts.free import DenseReport
from services.common.geometry.free_camera import quaternion_of_rotation, rotation_of_quaternion

__all__ = [
    "ANSWER",
    "BASELINE",
    "BOUND",
    "BOXES",
    "LENSES",
    "ROLLS",
    "METHODS",
    "CameraRecord",
    "FreeRecord",
    "Outcome",
    "camera_of",
    "camera_record",
]

ANSWER: Final = "answer"
"""The search's answer (``result.free.pose``)."""
BOXES: Final = "boxes"
"""The pose the search rendered first: its estimate from the target's boxes alone."""
BASELINE: Final = "baseline"
"""Plain ``cv2.solvePnPRansac`` on the detector's box centres (:mod:`.baseline`)."""
BOUND: Final = "box-only bound"
"""The ideal box-only fit (:func:`cosmos.bench.free_targets.solve.box_only_bound`)."""
METHODS: Final = (ANSWER, BOXES, BASELINE, BOUND)
LENSES: Final = ("narrower", "±30 %", "wider", "unknown")
ROLLS: Final = ("±25°", "25-60°", "60-90°", "beyond 90°", "unknown")
"""The targets' roll bands (issue 23's ±25°, then ``cosmos bench --free --roll-limit``'s)."""
_ROLL_TOPS: Final = (("±25°", 25.0), ("25-60°", 60.0), ("60-90°", 90.0))
"""The roll bands of :data:`ROLLS` up to their largest |roll| (degrees)."""

Outcome = Literal["found", "ambiguous", "failed", "error"]
"""``found``: the search succeeded with a confirmed ``found`` free answer; ``ambiguous``: it
answered a pose it does not vouch for; ``failed``: it ended without a pose; ``error``: the
bench could not run it (refused, lost, timed out)."""


class CameraRecord(FrozenModel):
    """A camera: centre (scene units), camera-to-world quaternion ``(w, x, y, z)``, horizontal
    fov in degrees."""

    position: tuple[float, float, float]
    quaternion_wxyz: tuple[float, float, float, float]
    fov_deg: float

    def estimate(self) -> Estimate:
        return Estimate(
            rotation_of_quaternion(self.quaternion_wxyz),
            np.asarray(self.position, dtype=np.float64),
            self.fov_deg,
        )


def camera_record(estimate: Estimate | None) -> CameraRecord | None:
    """``estimate`` as a record (None stays None)."""
    return None if estimate is None else camera_of(estimate)


def camera_of(estimate: Estimate) -> CameraRecord:
    """``estimate`` as a record."""
    p = estimate.position
    return CameraRecord(
        position=(float(p[0]), float(p[1]), float(p[2])),
        quaternion_wxyz=quaternion_of_rotation(estimate.rotation),
        fov_deg=float(estimate.fov_deg),
    )


class FreeRecord(FrozenModel):
    """One free target of one variant, searched through the stack (timings in ms)."""

    scene: str
    random: bool
    """A scene the bench generated (else a built-in one)."""
    onboarded: bool = False
    """Searched with the generated scene's own detector, after onboarding it (else a generated
    scene's searches use the general model; a built-in scene's, its own)."""
    variant: str
    index: int
    band: str
    elevation_deg: float
    intrinsics_given: bool
    objects: int
    """Objects at least 60 % visible in the (unchanged) view."""
    radius: float
    change: str = ""
    truth: CameraRecord
    fov_factor: float | None = None
    """The target lens' horizontal fov over the scene camera's (``cosmos bench --free
    --fov-range``; None in reports made before it was recorded)."""
    roll_deg: float | None = None
    """The target camera's roll about its optical axis (``--roll-limit``; None in reports made
    before it was recorded)."""
    search_id: str | None = None
    status: str
    """The search's status (``error`` when the bench could not run it)."""
    outcome: Outcome
    reason: str = ""
    steps: tuple[str, ...] = ()
    """Each render's reason, as its iteration says it (how its boxes and edges agreed)."""
    intrinsics_source: str | None = None
    """``given``, ``estimated`` or ``scene``: the intrinsics the answer was computed with."""
    detections: int = 0
    """How many detections the search recorded for the target."""
    target_detections: tuple[Detection, ...] = ()
    """The target's detections themselves, in pixels of its ``target_size`` image: what the box
    solve saw, for replaying it offline (``python -m benchmarks.free_replay``)."""
    target_size: tuple[int, int] | None = None
    renders: int = 0
    wall_ms: float = 0.0
    render_ms: float = 0.0
    """The search's own renders, detections of its views and optimizer calls, as its
    iterations' timings say, and the refit render's after them (the target's detection is not
    among them)."""
    detect_ms: float = 0.0
    optimize_ms: float = 0.0
    refine_ms: float = 0.0
    """The dense refinements by the search's renders (each alongside a view detection)."""
    floor_detect_ms: float | None = None
    floor_render_ms: float | None = None
    floor_view_detect_ms: float | None = None
    poses: dict[str, CameraRecord | None]
    """Per method of :data:`METHODS`: its pose (None: it gave none)."""
    dense: DenseReport | None = None
    """How the answer's dense refinement went (``result.free.dense``), when one was made."""

    @property
    def floor_ms(self) -> float | None:
        """Detect the target + one render + one detect, through the same services."""
        parts = (self.floor_detect_ms, self.floor_render_ms, self.floor_view_detect_ms)
        return None if any(p is None for p in parts) else sum(p for p in parts if p is not None)

    @property
    def detector(self) -> str:
        """``own`` (the scene's own model) or ``general`` (the shipped shape model)."""
        return "general" if self.random and not self.onboarded else "own"

    @property
    def lens(self) -> str:
        """The lens against the scene camera's: within issue 23's ±30 % of its fov, narrower or
        wider (``unknown`` in older reports)."""
        low, high = FOV_RANGE  # issue 23's lenses
        if self.fov_factor is None:
            return "unknown"
        if self.fov_factor < low:
            return "narrower"
        return "wider" if self.fov_factor > high else "±30 %"

    @property
    def roll(self) -> str:
        """The target's roll band (:data:`ROLLS`)."""
        if self.roll_deg is None:
            return "unknown"
        r = abs(self.roll_deg)
        return next((band for band, top in _ROLL_TOPS if r <= top), "beyond 90°")

    @property
    def given(self) -> str:
        return "fov given" if self.intrinsics_given else "fov not given"

    def error(self, method: str) -> PoseError:
        """``method``'s errors against the truth (infinite without a pose)."""
        pose = self.poses.get(method)
        return pose_error(
            pose.estimate() if pose is not None else None, self.truth.estimate(), self.radius
        )
