"""A small anchor-free, YOLO-style single-shot detector in plain PyTorch.

Backbone of strided conv + CSP blocks, a PAN neck, and one decoupled head per level at strides
8, 16 and 32. Each anchor point (the centre of a grid cell) predicts the distances (l, t, r, b)
from itself to the box sides and one score per class. :meth:`Detector.forward` returns the raw
per-level maps for training; :meth:`Detector.decode` turns them into the YOLOv8 export layout
``[B, 4 + num_classes, N]`` of (cx, cy, w, h) in input pixels followed by sigmoid class scores,
which is what the exported ONNX graph outputs and the detector service runs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["STRIDES", "Detector", "anchor_points"]

STRIDES: tuple[int, ...] = (8, 16, 32)


class ConvBnAct(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, k: int = 3, s: int = 1) -> None:
        super().__init__(
            nn.Conv2d(c_in, c_out, k, s, k // 2, bias=False),
            nn.BatchNorm2d(c_out),
            nn.SiLU(inplace=True),
        )


class Bottleneck(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.a = ConvBnAct(c, c, 3)
        self.b = ConvBnAct(c, c, 3)

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = x + self.b(self.a(x))
        return out


class CSPBlock(nn.Module):
    """Split channels, run bottlenecks on one half, concatenate, mix (YOLO's C2f, reduced)."""

    def __init__(self, c_in: int, c_out: int, n: int = 1) -> None:
        super().__init__()
        hidden = c_out // 2
        self.left = ConvBnAct(c_in, hidden, 1)
        self.right = ConvBnAct(c_in, hidden, 1)
        self.blocks = nn.Sequential(*[Bottleneck(hidden) for _ in range(n)])
        self.mix = ConvBnAct(2 * hidden, c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = self.mix(torch.cat([self.blocks(self.left(x)), self.right(x)], dim=1))
        return out


class SPPF(nn.Module):
    """Spatial pyramid pooling (fast): widens the receptive field of the deepest level."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.reduce = ConvBnAct(c, c // 2, 1)
        self.mix = ConvBnAct(c * 2, c, 1)

    def forward(self, x: Tensor) -> Tensor:
        x = self.reduce(x)
        y1 = F.max_pool2d(x, 5, 1, 2)
        y2 = F.max_pool2d(y1, 5, 1, 2)
        y3 = F.max_pool2d(y2, 5, 1, 2)
        out: Tensor = self.mix(torch.cat([x, y1, y2, y3], dim=1))
        return out


class Head(nn.Module):
    """Decoupled head: a box branch (4 distances) and a class branch (logits)."""

    def __init__(self, c: int, num_classes: int, width: int = 64) -> None:
        super().__init__()
        self.box = nn.Sequential(
            ConvBnAct(c, width), ConvBnAct(width, width), nn.Conv2d(width, 4, 1)
        )
        self.cls = nn.Sequential(
            ConvBnAct(c, width), ConvBnAct(width, width), nn.Conv2d(width, num_classes, 1)
        )
        # Start with low class probabilities (focal-loss style prior) and unit-size boxes.
        nn.init.constant_(self.cls[-1].bias, -4.6)  # type: ignore[arg-type]
        nn.init.constant_(self.box[-1].bias, 1.0)  # type: ignore[arg-type]

    def forward(self, x: Tensor) -> Tensor:
        return torch.cat([self.box(x), self.cls(x)], dim=1)


def anchor_points(
    height: int, width: int, device: torch.device | None = None
) -> tuple[Tensor, Tensor]:
    """Anchor centres ``(N, 2)`` in input pixels and their strides ``(N,)``, level by level."""
    points, strides = [], []
    for stride in STRIDES:
        h, w = height // stride, width // stride
        ys, xs = torch.meshgrid(
            torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij"
        )
        grid = torch.stack([xs, ys], dim=-1).reshape(-1, 2).float()
        points.append((grid + 0.5) * stride)
        strides.append(torch.full((h * w,), float(stride), device=device))
    return torch.cat(points), torch.cat(strides)


class Detector(nn.Module):
    """The detector; ``width`` scales every channel count."""

    def __init__(self, num_classes: int, width: int = 32) -> None:
        super().__init__()
        c1, c2, c3, c4, c5 = width // 2, width, width * 2, width * 4, width * 6
        self.num_classes = num_classes
        self.width = width
        self.stem = nn.Sequential(ConvBnAct(3, c1, 3, 2), ConvBnAct(c1, c2, 3, 2), CSPBlock(c2, c2))
        self.down3 = nn.Sequential(ConvBnAct(c2, c3, 3, 2), CSPBlock(c3, c3, 2))
        self.down4 = nn.Sequential(ConvBnAct(c3, c4, 3, 2), CSPBlock(c4, c4, 2))
        self.down5 = nn.Sequential(ConvBnAct(c4, c5, 3, 2), CSPBlock(c5, c5), SPPF(c5))
        self.lat5 = ConvBnAct(c5, c4, 1)
        self.top4 = CSPBlock(c4 * 2, c4)
        self.lat4 = ConvBnAct(c4, c3, 1)
        self.top3 = CSPBlock(c3 * 2, c3)
        self.bottom3 = ConvBnAct(c3, c3, 3, 2)
        self.out4 = CSPBlock(c3 + c3, c4)
        self.bottom4 = ConvBnAct(c4, c4, 3, 2)
        self.out5 = CSPBlock(c4 + c4, c5)
        self.heads = nn.ModuleList(
            [Head(c3, num_classes), Head(c4, num_classes), Head(c5, num_classes)]
        )

    def forward(self, x: Tensor) -> list[Tensor]:
        """Raw maps per level: ``[B, 4 + C, H/s, W/s]`` for s in :data:`STRIDES`."""
        p3 = self.down3(self.stem(x))
        p4 = self.down4(p3)
        p5 = self.down5(p4)
        l5 = self.lat5(p5)
        t4 = self.top4(torch.cat([F.interpolate(l5, scale_factor=2.0), p4], dim=1))
        l4 = self.lat4(t4)
        n3 = self.top3(torch.cat([F.interpolate(l4, scale_factor=2.0), p3], dim=1))
        n4 = self.out4(torch.cat([self.bottom3(n3), l4], dim=1))
        n5 = self.out5(torch.cat([self.bottom4(n4), l5], dim=1))
        return [head(f) for head, f in zip(self.heads, (n3, n4, n5), strict=True)]

    @staticmethod
    def flatten(maps: list[Tensor]) -> Tensor:
        """Per-level maps to ``[B, N, 4 + C]`` in anchor order."""
        return torch.cat([m.flatten(2) for m in maps], dim=2).transpose(1, 2)

    @staticmethod
    def distances(raw_box: Tensor, strides: Tensor) -> Tensor:
        """Raw box outputs to (l, t, r, b) distances in pixels (softplus keeps them positive)."""
        return F.softplus(raw_box) * strides[:, None]

    def decode(self, maps: list[Tensor], height: int, width: int) -> Tensor:
        """The export layout ``[B, 4 + C, N]``: (cx, cy, w, h) in input pixels, class scores."""
        flat = self.flatten(maps)
        points, strides = anchor_points(height, width, flat.device)
        ltrb = self.distances(flat[..., :4], strides)
        x1y1 = points - ltrb[..., :2]
        x2y2 = points + ltrb[..., 2:]
        boxes = torch.cat([(x1y1 + x2y2) / 2, x2y2 - x1y1], dim=-1)
        scores = flat[..., 4:].sigmoid()
        return torch.cat([boxes, scores], dim=-1).transpose(1, 2)


class ExportWrapper(nn.Module):
    """What goes into the ONNX file: image tensor in, decoded predictions out."""

    def __init__(self, model: Detector, height: int, width: int) -> None:
        super().__init__()
        self.model = model
        self.height = height
        self.width = width

    def forward(self, images: Tensor) -> Tensor:
        return self.model.decode(self.model(images), self.height, self.width)
