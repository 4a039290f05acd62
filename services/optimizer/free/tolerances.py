"""How far a box may lie from where a pose puts it, in pixels of the detector's input.

The detector sees a target letterboxed into its network input, so its box errors, measured in
those pixels, grow in the target's with the image it shrank (:func:`pixel_scale`). The pose
from boxes (:mod:`.solve`) works in the detector's pixels, so that one view is judged alike at
any resolution.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.optimizer.free.refine import PoseFit
from services.optimizer.geometry import FloatArray

__all__ = [
    "box_diagonals",
    "INLIER_BOX_FRACTION",
    "INLIER_MIN_PX",
    "NOISE_FLOOR_PX",
    "inlier_gate",
    "pixel_scale",
    "truncated_cost",
]

NOISE_FLOOR_PX: Final = 0.7
"""Edge RMS that any pose is granted: about the detector's measured box-edge error."""
INLIER_MIN_PX: Final = 3.0
INLIER_BOX_FRACTION: Final = 0.15


def box_diagonals(boxes: FloatArray) -> FloatArray:
    """The diagonals (pixels) of ``(..., 4)`` boxes ``(x1, y1, x2, y2)``."""
    d: FloatArray = np.hypot(boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1])
    return d


def inlier_gate(boxes: FloatArray) -> FloatArray:
    """(D,) the largest edge RMS (pixels) at which a refined pose's box still pairs with a
    detection: :data:`INLIER_BOX_FRACTION` of its diagonal, at least :data:`INLIER_MIN_PX`
    (partly hidden objects' boxes shrink)."""
    gate: FloatArray = np.maximum(INLIER_MIN_PX, INLIER_BOX_FRACTION * box_diagonals(boxes))
    return gate


def pixel_scale(image_size: tuple[int, int], detector_input: tuple[int, int] | None) -> float:
    """Target pixels per pixel of the detector's input: the detector saw the ``image_size``
    image letterboxed into ``detector_input`` (both ``(width, height)``), shrunk by ``min(w_in /
    W, h_in / H)``; 1 when that is unknown or the image is no larger (an image blown up is not
    sharper for it)."""
    if detector_input is None:
        return 1.0
    shrink = min(detector_input[0] / image_size[0], detector_input[1] / image_size[1])
    return max(1.0, 1.0 / shrink)


def truncated_cost(fit: PoseFit, detections: NDArray[np.intp], gates: FloatArray) -> float:
    """A ``fit``'s robust cost over all ``D`` usable detections (MSAC's truncated quadratic):
    ``Σ_paired min(r_i / g_i, 1)² + (D - pairs)``, ``r_i`` the box-edge RMS of its pair on
    ``detections[i]`` and ``g_i`` that detection's :func:`inlier_gate`; an unpaired detection
    costs as much as the worst pair. Ranking by pairs first let a wrong pose that pairs every
    box loosely beat the right one that leaves a moved object's box out: on a changed scene it
    was called found 20-125° away (``tests/optimizer/test_free_changed.py``)."""
    ratio = np.minimum(fit.pair_rms_px / gates[detections], 1.0)
    return float(np.sum(ratio**2)) + (len(gates) - len(detections))
