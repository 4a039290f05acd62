"""What a strategy is given (a search problem) and what it answers (a plan), as plain data."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import PaperCalibration
from services.optimizer.observations import Observation
from services.optimizer.view_cache import ViewMappings

__all__ = ["Estimate", "Move", "Plan", "SearchProblem", "Visit"]

Move = Literal["start", "stay", "N", "S", "E", "W", "jump"]


@dataclass(frozen=True)
class Visit:
    """A visited grid pose (flat index and angles, degrees) and its detections."""

    flat: int
    theta_deg: float
    phi_deg: float
    observation: Observation


@dataclass(frozen=True)
class SearchProblem:
    """One stateless planning step.

    Attributes
    ----------
    grid, camera
        The hemisphere grid and the camera (fov, film, radius).
    target : Observation
        Detections of the target image, camera pixels.
    history : tuple of Visit
        Visited poses in order; the last one is where the camera is now.
    tolerance_px : float
        RMS box-edge difference under which two views match (camera pixels).
    max_unmatched : int
        Summed confidence of the detections per image allowed to go unpaired in a match.
    ambiguity_ratio : float
        Candidates scoring within this factor of the best (plus a small margin) look alike.
    calibration : PaperCalibration or None
        The paper mapping's coefficients for this camera, when stored.
    mappings : ViewMappings or None
        Where the views' exact mappings are cached (None: the process's shared cache).
    """

    grid: HemisphereGrid
    camera: CameraSpec
    target: Observation
    history: tuple[Visit, ...]
    tolerance_px: float = 1.0
    max_unmatched: int = 1
    ambiguity_ratio: float = 1.25
    calibration: PaperCalibration | None = None
    mappings: ViewMappings | None = None

    @property
    def current(self) -> Visit | None:
        return self.history[-1] if self.history else None


@dataclass(frozen=True)
class Estimate:
    """The current estimate of the target pose.

    ``flat`` is the grid pose nearest to the continuous ``(theta_deg, phi_deg)``;
    ``residual_px`` is the reprojection (or layout) residual in camera pixels.
    """

    flat: int
    theta_deg: float
    phi_deg: float
    residual_px: float | None
    confidence: float
    sigma_deg: float | None = None
    """The 1-σ angle of the view direction ``(θ, φ)``, when the estimate has one."""


@dataclass(frozen=True)
class Plan:
    """A strategy's answer: where to go next, whether the search is done, and why."""

    done: bool
    next_flat: int
    move: Move
    estimate: Estimate | None
    ambiguous: bool
    alternatives: tuple[tuple[int, float], ...]
    reason: str
    checks: tuple[int, ...] | None = None
    """For an ambiguous done plan, the grid poses whose views can settle it: rendered, and none
    matching the target, they leave this pose the answer (:mod:`~.strategies.settle`). None:
    no view can settle it (too few detections pin the pose)."""
    vindicated: bool = True
    """Whether checks ruled out by their views confirm this pose. False when the estimate itself
    prefers a check (:attr:`~.strategies.done.Rival.settled_by_views`): rendered, the check may
    still pass its own done test and end the search there, but its worse view does not make
    this pose right."""
