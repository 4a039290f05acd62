"""Detection metrics (numpy only): matching at an IoU threshold, precision, recall, AP50.

Ground-truth objects less visible than a threshold are "ignored": a prediction that matches one
is neither a true nor a false positive, and missing one is not a miss (the COCO "crowd" rule).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.detector import postprocess

__all__ = ["Evaluation", "box_iou"]

FloatArray = NDArray[np.float64]


def box_iou(a: NDArray[np.floating], b: NDArray[np.floating]) -> FloatArray:
    """IoU matrix ``[M, N]`` of boxes ``a [M, 4]`` and ``b [N, 4]`` as (x1, y1, x2, y2): the
    detector service's IoU (:func:`services.detector.postprocess.box_iou`), one row per box."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    iou: FloatArray = np.zeros((len(a), len(b)), dtype=np.float64)
    for row, box in enumerate(a):
        iou[row] = postprocess.box_iou(box, b)
    return iou


@dataclass
class Evaluation:
    """Accumulates images, then reports per-class and overall P/R/AP50 and centre errors."""

    classes: tuple[str, ...]
    iou_threshold: float = 0.5
    min_visible: float = 0.6
    _scores: list[list[float]] = field(default_factory=list)
    _hits: list[list[bool]] = field(default_factory=list)
    _gt_counts: list[int] = field(default_factory=list)
    _centre_errors: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._scores = [[] for _ in self.classes]
        self._hits = [[] for _ in self.classes]
        self._gt_counts = [0 for _ in self.classes]

    def add(
        self,
        pred_boxes: NDArray[np.floating],
        pred_scores: NDArray[np.floating],
        pred_classes: NDArray[np.integer],
        gt_boxes: NDArray[np.floating],
        gt_classes: NDArray[np.integer],
        gt_visible: NDArray[np.floating],
    ) -> None:
        """Match one image's predictions to its ground truth (greedy by score, same class)."""
        pred_boxes = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 4)
        gt_boxes = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4)
        gt_classes = np.asarray(gt_classes)
        counted = np.asarray(gt_visible) >= self.min_visible
        for c in gt_classes[counted]:
            self._gt_counts[int(c)] += 1
        ious = box_iou(pred_boxes, gt_boxes)
        taken = np.zeros(len(gt_boxes), dtype=bool)
        ignored = ~counted
        for i in np.argsort(-np.asarray(pred_scores), kind="stable"):
            c = int(pred_classes[i])
            same = gt_classes == c
            candidates = np.where(same & ~taken, ious[i], 0.0)
            j = int(np.argmax(candidates)) if len(candidates) else -1
            if j >= 0 and candidates[j] >= self.iou_threshold:
                taken[j] = True
                if ignored[j]:
                    continue  # found an object too hidden to count: neither right nor wrong
                self._scores[c].append(float(pred_scores[i]))
                self._hits[c].append(True)
                centre_p = (pred_boxes[i, :2] + pred_boxes[i, 2:]) / 2
                centre_g = (gt_boxes[j, :2] + gt_boxes[j, 2:]) / 2
                self._centre_errors.append(float(np.linalg.norm(centre_p - centre_g)))
            elif np.any(same & ignored & (ious[i] >= self.iou_threshold)):
                continue  # a duplicate on an ignored object
            else:
                self._scores[c].append(float(pred_scores[i]))
                self._hits[c].append(False)

    def report(self) -> dict[str, object]:
        """Per class and overall precision, recall and AP50; median/p95 centre error (px)."""
        per_class: dict[str, dict[str, float]] = {}
        all_tp = all_pred = all_gt = 0
        aps = []
        for c, name in enumerate(self.classes):
            hits = np.array(self._hits[c], dtype=bool)
            tp, npred, ngt = int(hits.sum()), len(hits), self._gt_counts[c]
            ap = _average_precision(np.array(self._scores[c]), hits, ngt)
            per_class[name] = {
                "precision": tp / npred if npred else 1.0,
                "recall": tp / ngt if ngt else 1.0,
                "ap50": ap,
                "objects": float(ngt),
            }
            if ngt:
                aps.append(ap)
            all_tp, all_pred, all_gt = all_tp + tp, all_pred + npred, all_gt + ngt
        errors = np.array(self._centre_errors) if self._centre_errors else np.array([np.nan])
        return {
            "precision": all_tp / all_pred if all_pred else 1.0,
            "recall": all_tp / all_gt if all_gt else 1.0,
            "map50": float(np.mean(aps)) if aps else 0.0,
            "objects": all_gt,
            "centre_error_median_px": float(np.median(errors)),
            "centre_error_p95_px": float(np.percentile(errors, 95)),
            "per_class": per_class,
        }


def _average_precision(scores: FloatArray, hits: NDArray[np.bool_], gt_count: int) -> float:
    """Area under the all-point interpolated precision-recall curve."""
    if gt_count == 0 or len(scores) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(hits[order])
    fp = np.cumsum(~hits[order])
    recall = tp / gt_count
    precision = tp / np.maximum(tp + fp, 1)
    recall = np.concatenate([[0.0], recall, [recall[-1]]])
    precision = np.concatenate([[1.0], precision, [0.0]])
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return float(np.sum((recall[1:] - recall[:-1]) * precision[1:]))
