"""Detections as arrays in the camera's pixels, and how alike two detections look.

Boxes arrive in the pixels of whatever image the detector saw; the optimizer works in the pixels
of the scene's camera (:class:`~services.common.scene.Camera`), so every box is scaled by
``(W_cam / W_img, H_cam / H_img)`` once, here.

Appearance
----------
Two detections can be the same object only with the same class label. Colours (mean sRGB of the
object's pixels) vary with shading from view to view, so they are compared by chromaticity
``(R, G, B) / (R + G + B)``, which a change of brightness leaves alone; the cost is the
chromaticity distance over :data:`COLOUR_SCALE`, 0 when either colour is unknown.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.models import Detection
from services.common.scene import Camera
from services.optimizer.geometry import FloatArray
from services.optimizer.proxies import kind_of

__all__ = [
    "ALIKE_COST",
    "COLOUR_SCALE",
    "FORBIDDEN",
    "Observation",
    "appearance_cost",
    "chromaticity",
]

COLOUR_SCALE: Final = 0.06
"""Chromaticity distance that costs 1 (about the gap between orange and yellow)."""

ALIKE_COST: Final = 1.0
"""Detections of one class whose colour cost is below this look alike."""

FORBIDDEN: Final = 1e9
"""Cost of pairing detections of different classes."""


def chromaticity(colors: ArrayLike) -> FloatArray:
    """``(..., 3)`` sRGB colours to ``(..., 3)`` chromaticities; NaN stays NaN, black is grey."""
    c = np.asarray(colors, dtype=np.float64)
    total = c.sum(axis=-1, keepdims=True)
    out: FloatArray = np.divide(c, total, out=np.full_like(c, 1.0 / 3.0), where=total > 1e-9)
    out[np.isnan(c).any(axis=-1)] = np.nan
    return out


@dataclass(frozen=True, eq=False)
class Observation:
    """The detections of one image, in the camera's pixels.

    Compared and hashed by identity, so derived quantities can be cached per observation.

    Attributes
    ----------
    labels : tuple of str
        Class per detection.
    boxes : ndarray, shape (n, 4)
        ``[x1, y1, x2, y2]`` in camera pixels.
    colors : ndarray, shape (n, 3)
        Mean sRGB colour (0–255), NaN rows when unknown.
    confidence : ndarray, shape (n,)
        Detector confidence.
    """

    labels: tuple[str, ...]
    boxes: FloatArray
    colors: FloatArray
    confidence: FloatArray

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def kinds(self) -> NDArray[np.int_]:
        """:class:`~.proxies.ProxyKind` per detection."""
        return np.array([kind_of(label) for label in self.labels], dtype=np.int_)

    @property
    def centres(self) -> FloatArray:
        """Box centres ``(n, 2)``."""
        return (self.boxes[:, :2] + self.boxes[:, 2:]) / 2.0

    @classmethod
    def empty(cls) -> Observation:
        return cls((), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0))

    @classmethod
    def from_arrays(
        cls,
        labels: Sequence[str],
        boxes: ArrayLike,
        colors: ArrayLike | None = None,
        confidence: ArrayLike | None = None,
    ) -> Observation:
        """An observation from camera-pixel boxes ``(n, 4)`` and optional colours/confidences."""
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        n = len(b)
        if len(labels) != n:
            raise ValueError(f"{len(labels)} labels for {n} boxes")
        c = np.full((n, 3), np.nan) if colors is None else np.asarray(colors, dtype=np.float64)
        p = np.ones(n) if confidence is None else np.asarray(confidence, dtype=np.float64)
        return cls(tuple(labels), b, c.reshape(n, 3), p.reshape(n))

    @classmethod
    def from_detections(
        cls, detections: Sequence[Detection], image_size: tuple[int, int], camera: Camera
    ) -> Observation:
        """Scale detections of an image of ``image_size`` (width, height) to camera pixels."""
        sx = camera.width / image_size[0]
        sy = camera.height / image_size[1]
        boxes = np.array([d.box for d in detections], dtype=np.float64).reshape(-1, 4)
        boxes = boxes * np.array([sx, sy, sx, sy])
        colors = np.array(
            [d.color if d.color is not None else (np.nan,) * 3 for d in detections],
            dtype=np.float64,
        ).reshape(-1, 3)
        return cls(
            labels=tuple(d.label for d in detections),
            boxes=boxes,
            colors=colors,
            confidence=np.array([d.confidence for d in detections], dtype=np.float64),
        )

    def subset(self, keep: ArrayLike) -> Observation:
        """The detections selected by a boolean mask or index array."""
        idx = np.arange(len(self))[np.asarray(keep)]
        return Observation(
            labels=tuple(self.labels[i] for i in idx),
            boxes=self.boxes[idx],
            colors=self.colors[idx],
            confidence=self.confidence[idx],
        )


def appearance_cost(
    labels_a: Sequence[str],
    colors_a: ArrayLike,
    labels_b: Sequence[str],
    colors_b: ArrayLike,
) -> FloatArray:
    """``(n, m)`` cost of pairing detections: :data:`FORBIDDEN` across classes, else the
    chromaticity distance over :data:`COLOUR_SCALE` (0 when a colour is unknown)."""
    la = np.asarray(labels_a, dtype=object).reshape(-1, 1)
    lb = np.asarray(labels_b, dtype=object).reshape(1, -1)
    same = la == lb
    ca = chromaticity(np.asarray(colors_a, dtype=np.float64).reshape(-1, 3))[:, np.newaxis, :]
    cb = chromaticity(np.asarray(colors_b, dtype=np.float64).reshape(-1, 3))[np.newaxis, :, :]
    distance = np.sqrt(np.sum((ca - cb) ** 2, axis=-1)) / COLOUR_SCALE
    return np.where(same, np.where(np.isnan(distance), 0.0, distance), FORBIDDEN)
