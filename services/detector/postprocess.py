"""Turn a YOLO head's raw output into boxes: decode, threshold, per-class NMS.

The output of one image is ``(4 + C, N)``: for each of N anchors the box centre, width and height
``(cx, cy, w, h)`` in input pixels, then C class scores in [0, 1] (already through the sigmoid) -
the layout of Ultralytics' YOLOv8/YOLO11 ONNX export. Each anchor votes for its best class only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["Candidates", "box_iou", "decode_output", "nms"]


@dataclass(frozen=True)
class Candidates:
    """Boxes ``(K, 4)`` as ``x1, y1, x2, y2`` (pixel edges), their scores ``(K,)`` and class ids
    ``(K,)``, best score first."""

    boxes: NDArray[np.float64]
    scores: NDArray[np.float64]
    class_ids: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def take(self, index: NDArray[np.intp]) -> Candidates:
        """The candidates at ``index``, in that order."""
        return Candidates(self.boxes[index], self.scores[index], self.class_ids[index])


def decode_output(
    output: NDArray[np.floating], conf_threshold: float, max_candidates: int
) -> Candidates:
    """The anchors of one image's output ``(4 + C, N)`` whose best class score is at least
    ``conf_threshold``, as corner boxes in input pixels; at most ``max_candidates`` of them (the
    best). Non-finite values and empty boxes are dropped."""
    if output.ndim != 2 or output.shape[0] < 5:
        raise ValueError(f"expected a (4 + C, N) output with C >= 1, got {output.shape}")
    scores_all = output[4:]
    class_ids = np.argmax(scores_all, axis=0)
    scores = np.take_along_axis(scores_all, class_ids[None, :], axis=0)[0]
    cx, cy, w, h = output[0], output[1], output[2], output[3]
    keep = (
        (scores >= conf_threshold)
        & np.isfinite(scores)
        & np.isfinite(output[:4]).all(axis=0)
        & (w > 0)
        & (h > 0)
    )
    index = np.flatnonzero(keep)
    order = np.argsort(-scores[index].astype(np.float64), kind="stable")[:max_candidates]
    index = index[order]
    cx, cy, half_w, half_h = (
        cx[index].astype(np.float64),
        cy[index].astype(np.float64),
        w[index].astype(np.float64) / 2.0,
        h[index].astype(np.float64) / 2.0,
    )
    boxes = np.stack([cx - half_w, cy - half_h, cx + half_w, cy + half_h], axis=1)
    return Candidates(
        boxes=boxes.reshape(-1, 4),
        scores=scores[index].astype(np.float64),
        class_ids=class_ids[index].astype(np.int64),
    )


def box_iou(box: NDArray[np.float64], boxes: NDArray[np.float64]) -> NDArray[np.float64]:
    """Intersection over union of one box ``(4,)`` with each of ``boxes`` ``(K, 4)``."""
    ix = np.clip(np.minimum(box[2], boxes[:, 2]) - np.maximum(box[0], boxes[:, 0]), 0.0, None)
    iy = np.clip(np.minimum(box[3], boxes[:, 3]) - np.maximum(box[1], boxes[:, 1]), 0.0, None)
    inter = ix * iy
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    union = area + areas - inter
    out: NDArray[np.float64] = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0.0)
    return out


def nms(
    candidates: Candidates,
    iou_threshold: float,
    max_detections: int,
    cross_class_iou: float | None = None,
) -> Candidates:
    """Greedy non-maximum suppression within each class, and optionally across classes.

    Best score first, a box is kept and every box of the *same class* overlapping it by
    IoU > ``iou_threshold`` is dropped; a box of *another* class is dropped only when it
    overlaps by IoU > ``cross_class_iou`` (None: never). Stops after ``max_detections`` boxes.
    Ties in score keep their input order.
    """
    order = np.argsort(-candidates.scores, kind="stable")
    boxes, class_ids = candidates.boxes, candidates.class_ids
    kept: list[int] = []
    while order.size and len(kept) < max_detections:
        best, rest = int(order[0]), order[1:]
        kept.append(best)
        same = class_ids[rest] == class_ids[best]
        iou = box_iou(boxes[best], boxes[rest])
        dropped = same & (iou > iou_threshold)
        if cross_class_iou is not None:
            dropped |= iou > cross_class_iou
        order = rest[~dropped]
    return candidates.take(np.asarray(kept, dtype=np.intp))
