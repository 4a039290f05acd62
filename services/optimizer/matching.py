"""Correspondence between detections: gated Hungarian assignment and view-to-view comparison.

Correspondence never uses ground truth: pairs must look alike — colour, and class: equal object
classes with a scene's own detector, shape classes as a soft cost with the general one
(:mod:`.observations`) — and geometry (box positions) decides among the rest. The assignment
minimises ``Σ min(c_ij, g)`` over one-to-one pairs (``g`` the gate), which is the Hungarian
problem with every detection free to stay unmatched at cost ``g``; pairs at or over the gate are
then dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
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
    "without_changed_object",
    "without_worst_pair",
]

MIN_PAIRS_LEFT: Final = 3
"""Pairs that must stay when :func:`without_worst_pair` leaves one out."""

PAIR_GATE_PX: Final = 16.0
"""Boxes further apart than this (RMS of the edges, pixels) are never paired between views."""

COLOUR_GATE: Final = 3.0
"""Appearance cost (colour in units of :data:`~.observations.COLOUR_SCALE`, plus any class
mismatch cost) above which two detections are taken to be different objects."""


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
    unpaired_a, unpaired_b : float
        Their summed confidence: a doubtful detection without a partner is weak evidence that
        the views differ.
    noise_px : float
        Expected RMS edge difference of the pairs from detection noise alone,
        ``√(mean_j (σ_aj² + σ_bj²))`` (:func:`~.observations.edge_sigma`; 0 without pairs).
    paired_weight : float
        Share of the two images' summed confidence that is paired, in [0, 1].
    """

    pairs: Assignment
    rms_px: float
    unmatched_a: int
    unmatched_b: int
    unpaired_a: float = 0.0
    unpaired_b: float = 0.0
    noise_px: float = 0.0
    paired_weight: float = 0.0
    changed: str = ""
    """The unpaired detections of one object left out of the comparison
    (:func:`without_changed_object`), in words; empty when none was."""

    def tolerance(self, rms_px: float, sigmas: float) -> float:
        """``√(rms_px² + (sigmas · noise_px)²)``: a tolerance grown by the pairs' noise."""
        return math.hypot(rms_px, sigmas * self.noise_px)

    def paired(self, max_unmatched: float) -> bool:
        """Whether each image's unpaired detections weigh at most ``max_unmatched``."""
        return self.unpaired_a <= max_unmatched and self.unpaired_b <= max_unmatched

    def within(self, rms_px: float, max_unmatched: float) -> bool:
        """Whether the views match: RMS within ``rms_px`` and unpaired detections weighing at
        most ``max_unmatched`` (summed confidence) in each image."""
        return len(self.pairs) > 0 and self.rms_px <= rms_px and self.paired(max_unmatched)

    def score(self, tolerance_px: float) -> float:
        """How well the views match, in [0, 1]: the paired share of confidence times
        ``exp(−½ (rms / tolerance_px)²)`` (1 for identical views)."""
        if len(self.pairs) == 0:
            return 0.0
        return float(self.paired_weight * math.exp(-0.5 * (self.rms_px / tolerance_px) ** 2))


def compare_views(a: Observation, b: Observation, gate_px: float = PAIR_GATE_PX) -> ViewComparison:
    """Match two images' detections by class, colour and box position.

    Pair cost is ``rms/g + appearance cost`` (g = ``gate_px``); pairs whose appearance cost
    reaches :data:`COLOUR_GATE` (unlike colours, other object classes) or whose boxes are more
    than ``g`` apart (RMS) are never made.
    """
    distance = box_rms(a.boxes, b.boxes)
    mismatch = max(a.mismatch_cost, b.mismatch_cost)
    looks = appearance_cost(a.labels, a.colors, b.labels, b.colors, mismatch)
    cost = distance / gate_px + looks
    gate = 1.0 + COLOUR_GATE
    cost = np.where((looks < COLOUR_GATE) & (distance <= gate_px), cost, np.inf)
    return _comparison(a, b, assign(cost, gate), distance)


def _comparison(
    a: Observation, b: Observation, pairs: Assignment, distance: FloatArray
) -> ViewComparison:
    """The comparison of ``a`` and ``b`` made of ``pairs`` (``distance``: all boxes' RMS)."""
    matched = distance[pairs.rows, pairs.cols]
    rms = float(np.sqrt(np.mean(matched**2))) if len(matched) else float("inf")
    noise = 0.0
    if len(matched):
        variance = a.edge_sigma[pairs.rows] ** 2 + b.edge_sigma[pairs.cols] ** 2
        noise = float(np.sqrt(np.mean(variance)))
    total = float(a.confidence.sum() + b.confidence.sum())
    paired = float(a.confidence[pairs.rows].sum() + b.confidence[pairs.cols].sum())
    return ViewComparison(
        pairs=pairs,
        rms_px=rms,
        unmatched_a=len(a) - len(pairs),
        unmatched_b=len(b) - len(pairs),
        unpaired_a=float(a.confidence.sum()) - float(a.confidence[pairs.rows].sum()),
        unpaired_b=float(b.confidence.sum()) - float(b.confidence[pairs.cols].sum()),
        noise_px=noise,
        paired_weight=paired / total if total > 0.0 else 0.0,
    )


def without_worst_pair(
    a: Observation, b: Observation, comparison: ViewComparison, max_unmatched: float
) -> ViewComparison | None:
    """``comparison`` with its worst pair (largest box RMS) left unpaired, when at least
    :data:`MIN_PAIRS_LEFT` pairs stay and both images' unpaired confidence, the pair's added,
    stays within ``max_unmatched``; else None.

    One pair of a true match can be far off while the rest agree to a pixel: an object moved
    since the scene file (the ``changed`` target), or a general detector's doubtful box put on
    another part of an object in one image (a partly visible object boxed as a cone here and a
    cube there, 15 px apart). Its two detections then count as unpaired, which the done test
    already allows up to ``max_unmatched`` of summed confidence in each image; the other pairs,
    at least three objects, still pin the pose."""
    pairs = comparison.pairs
    if len(pairs) < MIN_PAIRS_LEFT + 1:
        return None
    distance = box_rms(a.boxes, b.boxes)
    worst = int(np.argmax(distance[pairs.rows, pairs.cols]))
    if (
        comparison.unpaired_a + float(a.confidence[pairs.rows[worst]]) > max_unmatched
        or comparison.unpaired_b + float(b.confidence[pairs.cols[worst]]) > max_unmatched
    ):
        return None
    keep = np.arange(len(pairs)) != worst
    kept = Assignment(pairs.rows[keep], pairs.cols[keep], pairs.costs[keep])
    return _comparison(a, b, kept, distance)


def without_changed_object(
    a: Observation, b: Observation, comparison: ViewComparison
) -> ViewComparison | None:
    """``comparison`` with the unpaired detections of one object left out of its unpaired
    confidence, when at least :data:`MIN_PAIRS_LEFT` pairs pin the pose; else None.

    The site changed since its scene file: one object moved far (a detection without a partner
    in each image, alike in class and colour), or left (one in ``a``, the rendered view, alone),
    or came (one in ``b``, the photo, alone). Those detections then weigh as unpaired, often
    beyond the done test's ``max_unmatched``, though the other objects agree to a pixel. The
    one object left out is the choice of the three that leaves the larger of the two images'
    unpaired confidence smallest; :func:`without_worst_pair` covers the object moved a little
    (still paired, off)."""
    pairs = comparison.pairs
    if len(pairs) < MIN_PAIRS_LEFT:
        return None
    alone_a = np.setdiff1d(np.arange(len(a)), pairs.rows)
    alone_b = np.setdiff1d(np.arange(len(b)), pairs.cols)
    if len(alone_a) == 0 and len(alone_b) == 0:
        return None
    choices: list[tuple[int | None, int | None]] = []
    if len(alone_a):
        choices.append((int(alone_a[np.argmax(a.confidence[alone_a])]), None))
    if len(alone_b):
        choices.append((None, int(alone_b[np.argmax(b.confidence[alone_b])])))
    if len(alone_a) and len(alone_b):
        mismatch = max(a.mismatch_cost, b.mismatch_cost)
        looks = appearance_cost(
            [a.labels[i] for i in alone_a], a.colors[alone_a],
            [b.labels[j] for j in alone_b], b.colors[alone_b], mismatch,
        )  # fmt: skip
        weight = a.confidence[alone_a][:, np.newaxis] + b.confidence[alone_b][np.newaxis, :]
        weight = np.where(looks < COLOUR_GATE, weight, -np.inf)
        if np.isfinite(weight).any():
            row, col = np.unravel_index(int(np.argmax(weight)), weight.shape)
            choices.append((int(alone_a[row]), int(alone_b[col])))

    def left(choice: tuple[int | None, int | None]) -> tuple[float, float]:
        i, j = choice
        return (
            comparison.unpaired_a - (float(a.confidence[i]) if i is not None else 0.0),
            comparison.unpaired_b - (float(b.confidence[j]) if j is not None else 0.0),
        )

    chosen = min(choices, key=lambda c: max(left(c)))
    unpaired_a, unpaired_b = left(chosen)
    i, j = chosen
    if i is not None and j is not None:
        why = f"{a.labels[i]} ({a.confidence[i]:.2f}) moved since the scene file"
    elif i is not None:
        why = f"{a.labels[i]} ({a.confidence[i]:.2f}) not in the target: gone since the scene file"
    else:
        assert j is not None
        why = f"{b.labels[j]} ({b.confidence[j]:.2f}) of the target not in the scene file"
    return replace(
        comparison,
        unmatched_a=comparison.unmatched_a - (i is not None),
        unmatched_b=comparison.unmatched_b - (j is not None),
        unpaired_a=max(unpaired_a, 0.0),
        unpaired_b=max(unpaired_b, 0.0),
        changed=why,
    )
