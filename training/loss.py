"""Task-aligned label assignment and the detection loss (as in TOOD / YOLOv8, simplified).

For each ground-truth box, the candidate anchors are those whose centre lies inside the box
(grown by half the anchor's stride, so tiny objects still get one). Each candidate gets the
alignment ``t = s^α · IoU^β`` of its predicted score ``s`` for the box's class and the IoU of its
predicted box; the ``k`` best candidates become positives. Class targets are the alignment,
rescaled per box so its best anchor's target equals its best IoU; the class loss is binary cross
entropy over all anchors, the box loss GIoU weighted by those targets.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["detection_loss", "pairwise_iou"]

ALPHA, BETA, TOP_K = 0.5, 6.0, 10
BOX_WEIGHT, CLS_WEIGHT = 5.0, 1.0


def pairwise_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU of boxes ``a [..., M, 4]`` and ``b [..., N, 4]`` (x1, y1, x2, y2) -> ``[..., M, N]``."""
    lt = torch.maximum(a[..., :, None, :2], b[..., None, :, :2])
    rb = torch.minimum(a[..., :, None, 2:], b[..., None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[..., 2:] - a[..., :2]).clamp(min=0).prod(-1)
    area_b = (b[..., 2:] - b[..., :2]).clamp(min=0).prod(-1)
    return inter / (area_a[..., :, None] + area_b[..., None, :] - inter + 1e-9)


def _giou(a: Tensor, b: Tensor) -> Tensor:
    """Generalised IoU of matching boxes ``[..., 4]``."""
    lt = torch.maximum(a[..., :2], b[..., :2])
    rb = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    union = (a[..., 2:] - a[..., :2]).prod(-1) + (b[..., 2:] - b[..., :2]).prod(-1) - inter
    iou = inter / (union + 1e-9)
    hull = (torch.maximum(a[..., 2:], b[..., 2:]) - torch.minimum(a[..., :2], b[..., :2])).prod(-1)
    return iou - (hull - union) / (hull + 1e-9)


@torch.no_grad()
def _assign(
    scores: Tensor,
    boxes: Tensor,
    points: Tensor,
    strides: Tensor,
    gt_boxes: Tensor,
    gt_classes: Tensor,
    gt_mask: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Targets per anchor: class scores ``[B, N, C]``, boxes ``[B, N, 4]``, positive ``[B, N]``."""
    b, n, c = scores.shape
    m = gt_boxes.shape[1]
    grow = (strides / 2)[None, None, :, None]
    px, py = points[None, None, :, 0], points[None, None, :, 1]
    box = gt_boxes[:, :, None, :]
    inside = (
        (px > box[..., 0] - grow[..., 0])
        & (px < box[..., 2] + grow[..., 0])
        & (py > box[..., 1] - grow[..., 0])
        & (py < box[..., 3] + grow[..., 0])
        & gt_mask[:, :, None]
    )  # [B, M, N]
    ious = pairwise_iou(gt_boxes, boxes).clamp(min=0)  # [B, M, N]
    cls_index = gt_classes.clamp(min=0)[:, :, None].expand(b, m, n)
    cls_scores = scores.transpose(1, 2).gather(1, cls_index)  # [B, M, N]
    align = cls_scores.pow(ALPHA) * ious.pow(BETA) * inside
    top = align.topk(min(TOP_K, n), dim=-1).indices
    chosen = torch.zeros_like(align, dtype=torch.bool).scatter_(-1, top, True) & inside
    # An anchor chosen by several boxes keeps the one it overlaps most.
    several = chosen.sum(1, keepdim=True) > 1
    best = (ious * chosen).argmax(1, keepdim=True)
    sole = torch.zeros_like(chosen).scatter_(1, best, True)
    chosen = torch.where(several, sole & chosen, chosen)
    positive = chosen.any(1)  # [B, N]
    owner = chosen.float().argmax(1)  # [B, N]
    align = align * chosen
    norm = align / (align.amax(-1, keepdim=True) + 1e-9) * (ious * chosen).amax(-1, keepdim=True)
    strength = norm.amax(1)  # [B, N]
    target_boxes = gt_boxes.gather(1, owner[..., None].expand(b, n, 4))
    target_classes = gt_classes.gather(1, owner).clamp(min=0)
    target_scores = F.one_hot(target_classes, c).float() * (strength * positive)[..., None]
    return target_scores, target_boxes, positive


def detection_loss(
    raw: Tensor,
    points: Tensor,
    strides: Tensor,
    gt_boxes: Tensor,
    gt_classes: Tensor,
    gt_mask: Tensor,
) -> tuple[Tensor, dict[str, float]]:
    """The loss of flattened raw predictions ``[B, N, 4 + C]`` against padded ground truth.

    ``gt_boxes [B, M, 4]`` in input pixels, ``gt_classes [B, M]``, ``gt_mask [B, M]`` marks the
    real boxes among the padding.
    """
    ltrb = F.softplus(raw[..., :4]) * strides[None, :, None]
    boxes = torch.cat([points - ltrb[..., :2], points + ltrb[..., 2:]], dim=-1)
    logits = raw[..., 4:]
    target_scores, target_boxes, positive = _assign(
        logits.detach().sigmoid(), boxes.detach(), points, strides, gt_boxes, gt_classes, gt_mask
    )
    total = target_scores.sum().clamp(min=1.0)
    cls_loss = F.binary_cross_entropy_with_logits(logits, target_scores, reduction="sum") / total
    if positive.any():
        weight = target_scores.sum(-1)[positive]
        giou = _giou(boxes[positive], target_boxes[positive])
        box_loss = ((1.0 - giou) * weight).sum() / total
    else:
        box_loss = boxes.sum() * 0.0
    loss = BOX_WEIGHT * box_loss + CLS_WEIGHT * cls_loss
    return loss, {
        "box": float(box_loss.detach()),
        "cls": float(cls_loss.detach()),
        "pos": float(positive.sum()),
    }
