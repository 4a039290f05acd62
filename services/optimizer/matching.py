"""Correspondence between detections: gated Hungarian assignment and view-to-view comparison.

Correspondence never uses ground truth: pairs must share a class, colours must be alike
(:mod:`.observations`), and geometry (box positions) decides among the rest. The assignment
minimises ``Σ min(c_ij, g)`` over one-to-one pairs (``g`` the gate), which is the Hungarian
problem with every detection free to stay unmatched at cost ``g``; pairs at or over the gate are
then dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from services.optimizer.geometry import FloatArray
from services.optimizer.observations import Observation, appearance_cost

__all__ = [
    "COLOUR_GATE",
    "PAIR_GATE_PX",
    "Assignment",
    "ViewComparison",
    "assign",
    "box_rms",
    "compare_views",
]

PAIR_GATE_PX: Final = 16.0
"""Boxes further apart than this (RMS of the edges, pixels) are never paired between views."""

COLOUR_GATE: Final = 3.0
"""Colour cost (in units of :data:`~.observations.COLOUR_SCALE`) above which two detections of
one class are taken to be different objects."""


_LOWEST: Final = float(np.finfo(np.float64).min)


@dataclass(frozen=True)
class Assignment:
    """Matched pairs ``(rows[k], cols[k])`` and their costs."""

    rows: NDArray[np.intp]
    cols: NDArray[np.intp]
    costs: FloatArray

    def __len__(self) -> int:
        return len(self.rows)


def assign(cost: ArrayLike, gate: float) -> Assignment:
    """Gated one-to-one assignment minimising ``Σ min(c_ij, gate)`` (module docstring)."""
    c = np.asarray(cost, dtype=np.float64)
    if c.size == 0:
        empty = np.zeros(0, dtype=np.intp)
        return Assignment(empty, empty, np.zeros(0))
    # min(c, gate) with NaN and +inf as the gate and -inf as the lowest float (what
    # nan_to_num + minimum did, in fewer passes: score_poses assigns a dozen times a call).
    capped = np.maximum(np.where(c < gate, c, gate), _LOWEST)
    rows, cols = linear_sum_assignment(capped)
    picked = c[rows, cols]
    keep = picked < gate
    return Assignment(rows[keep], cols[keep], picked[keep])


def box_rms(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``(n, m)`` root mean square difference of the four edges of boxes ``(n, 4)``, ``(m, 4)``."""
    da = np.asarray(a, dtype=np.float64)[:, np.newaxis, :]
    db = np.asarray(b, dtype=np.float64)[np.newaxis, :, :]
    rms: FloatArray = np.sqrt(np.mean((da - db) ** 2, axis=-1))
    return rms


@dataclass(frozen=True)
class ViewComparison:
    """How two images' detections agree.

    Attributes
    ----------
    pairs : Assignment
        Matched detections (rows index the first image, cols the second).
    rms_px : float
        RMS edge difference over the matched boxes (inf when nothing matched).
    unmatched_a, unmatched_b : int
        Detections of each image without a partner.
    """

    pairs: Assignment
    rms_px: float
    unmatched_a: int
    unmatched_b: int

    def within(self, rms_px: float, max_unmatched: int) -> bool:
        """Whether the views match: RMS within ``rms_px`` and few unpaired detections."""
        return (
            len(self.pairs) > 0
            and self.rms_px <= rms_px
            and self.unmatched_a <= max_unmatched
            and self.unmatched_b <= max_unmatched
        )


def compare_views(a: Observation, b: Observation, gate_px: float = PAIR_GATE_PX) -> ViewComparison:
    """Match two images' detections by class, colour and box position.

    Pair cost is ``rms/g + colour cost`` (g = ``gate_px``); pairs of different classes, unlike
    colours (cost ≥ :data:`COLOUR_GATE`) or boxes more than ``g`` apart (RMS) are never made.
    """
    distance = box_rms(a.boxes, b.boxes)
    looks = appearance_cost(a.labels, a.colors, b.labels, b.colors)
    cost = distance / gate_px + looks
    gate = 1.0 + COLOUR_GATE
    cost = np.where((looks < COLOUR_GATE) & (distance <= gate_px), cost, np.inf)
    pairs = assign(cost, gate)
    matched = distance[pairs.rows, pairs.cols]
    rms = float(np.sqrt(np.mean(matched**2))) if len(matched) else float("inf")
    return ViewComparison(
        pairs=pairs,
        rms_px=rms,
        unmatched_a=len(a) - len(pairs),
        unmatched_b=len(b) - len(pairs),
    )
