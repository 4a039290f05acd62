"""Whether the render at a free pose shows what the target shows: its detections against the
target's, box by box.

The render is made at the pose with the intrinsics used, on a film the target's shape scaled by
``s`` (:func:`view_film`, the camera's pixel intrinsics scaled too: :func:`scaled_camera`); its
boxes are scaled back by ``1 / s``. Each target detection that the
pose paired with an object must be seen again in the render: a detection of the same label,
or named as the object the pose paired it with (the optimizer pairs a detection whose colour
contradicts its label with the object its colour names: the render's may name it right), whose
box-edge RMS from the target's is within the gate ``g_i = max(GATE_MIN_PX / min(s, 1),
GATE_FRACTION · diag_i)`` (``diag_i`` the target box's diagonal, ``GATE_MIN_PX / s`` one
render pixel's quantisation at the scale, doubled; never below two of the target's own pixels,
which a render larger than the target does not make finer). Pairs are drawn by the Hungarian method
(scipy's ``linear_sum_assignment``) on the edge RMS over the sides that touch neither image's
border (a clipped side says only that the object goes on).

The match's ``score`` is the share of the paired target detections reproduced times
``exp(−½ (rms / ḡ)²)``, ``ḡ`` the mean gate: 1 for identical boxes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from services.common.contracts.detect import Detection
from services.common.contracts.free import FreePose
from services.common.contracts.optimize import ViewMatch
from services.common.geometry.free_camera import FreeCamera

__all__ = [
    "GATE_FRACTION",
    "GATE_MIN_PX",
    "FreeMatch",
    "compare_view",
    "scaled_camera",
    "view_film",
]

GATE_FRACTION: Final = 0.1
"""Share of a target box's diagonal its render's box may be off by, edge RMS."""
GATE_MIN_PX: Final = 2.0
"""The smallest gate, in render pixels."""
EDGE_NOISE_PX: Final = 0.7
"""The detector's box-edge noise (pixels), as the optimizer takes it."""
_BORDER_PX: Final = 0.5

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FreeMatch:
    """How the render at a pose agrees with the target: ``agree`` when every paired target
    detection is seen again within its gate; ``match`` in the search's terms; ``missing`` the
    paired target detections not seen again."""

    agree: bool
    match: ViewMatch
    missing: tuple[int, ...]


def view_film(
    target_size: tuple[int, int], max_width: int, max_scale: float = 1.0
) -> tuple[tuple[int, int], float]:
    """The render's film for a target of ``target_size``: its shape, at most ``max_width``
    pixels wide and ``max_scale`` times the target's width, and the scale ``s`` from target to
    film."""
    width, height = target_size
    scale = min(max_scale, max_width / width)
    film = (max(8, round(width * scale)), max(8, round(height * scale)))
    return film, film[0] / width


def scaled_camera(pose: FreePose, scale: float) -> FreeCamera:
    """``pose``'s camera on a film ``scale`` times the target's: the pixel intrinsics scaled
    (the lens, on normalised coordinates, is unchanged)."""
    k = pose.intrinsics
    return pose.camera().model_copy(
        update={
            "fx_px": k.fx_px * scale,
            "fy_px": k.fy_px * scale,
            "cx_px": k.cx_px * scale,
            "cy_px": k.cy_px * scale,
        }
    )


def _boxes(detections: Sequence[Detection], factor: float) -> FloatArray:
    return np.array([d.box for d in detections], dtype=np.float64).reshape(-1, 4) * factor


def _border(boxes: FloatArray, width: float, height: float) -> NDArray[np.bool_]:
    limit = np.array([0.0, 0.0, width, height])
    low = boxes[:, :2] <= limit[:2] + _BORDER_PX
    high = boxes[:, 2:] >= limit[2:] - _BORDER_PX
    return np.concatenate([low, high], axis=1)


def compare_view(
    target: Sequence[Detection],
    target_size: tuple[int, int],
    paired: Sequence[int],
    view: Sequence[Detection],
    view_size: tuple[int, int],
    objects: Sequence[str] = (),
) -> FreeMatch:
    """The render's detections ``view`` (on a ``view_size`` film) against the ``paired``
    target detections (indices into ``target``), in target pixels (module docstring);
    ``objects`` the names of the objects they were paired with, in that order, when known."""
    width, height = target_size
    scale = view_size[0] / width
    names = dict(zip(paired, objects, strict=False))
    want = [i for i in paired if 0 <= i < len(target)]
    t = _boxes([target[i] for i in want], 1.0)
    v = _boxes(view, 1.0 / scale)
    gates = np.maximum(
        GATE_MIN_PX / min(scale, 1.0),
        GATE_FRACTION * np.hypot(t[:, 2] - t[:, 0], t[:, 3] - t[:, 1]),
    )
    masked = _border(t, width, height)[:, None, :] | _border(v, width, height)[None, :, :]
    diff = (t[:, None, :] - v[None, :, :]) ** 2
    diff[masked] = 0.0
    used = np.maximum((~masked).sum(axis=-1), 1)
    rms = np.sqrt(diff.sum(axis=-1) / used)
    accepted = [{target[i].label, names.get(i, target[i].label)} for i in want]
    same = np.array([[d.label in a for d in view] for a in accepted], dtype=np.bool_)
    cost = np.where(same.reshape(rms.shape) & (rms <= gates[:, None]), rms, 1e9)
    rows, cols = linear_sum_assignment(cost) if cost.size else (np.zeros(0, int), np.zeros(0, int))
    keep = cost[rows, cols] < 1e9
    rows, cols = rows[keep], cols[keep]
    seen = set(rows.tolist())
    missing = tuple(want[i] for i in range(len(want)) if i not in seen)
    pair_rms = rms[rows, cols]
    overall = float(math.sqrt(float(np.mean(pair_rms**2)))) if len(rows) else None
    share = len(rows) / len(want) if want else 0.0
    mean_gate = float(gates.mean()) if len(gates) else 1.0
    score = share * math.exp(-0.5 * ((overall or 0.0) / mean_gate) ** 2) if len(rows) else 0.0
    unpaired_view = [d.confidence for j, d in enumerate(view) if j not in set(cols.tolist())]
    match = ViewMatch(
        rms_px=overall,
        noise_px=EDGE_NOISE_PX * math.sqrt(2.0),
        pairs=len(rows),
        unpaired_current=float(sum(unpaired_view)),
        unpaired_target=float(sum(target[i].confidence for i in missing)),
        score=min(1.0, max(0.0, score)),
    )
    return FreeMatch(agree=bool(want) and not missing, match=match, missing=missing)
