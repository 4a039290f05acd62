"""Detections as arrays in the camera's pixels, and how alike two detections look.

Boxes arrive in the pixels of whatever image the detector saw; the optimizer works in the pixels
of the scene's camera (:class:`~services.common.geometry.scene.CameraSpec`), so every box is scaled
by ``(W_cam / W_img, H_cam / H_img)`` once, here.

Classes
-------
A label means one of two things. With the general detector it is a *shape class* (sphere, cube,
cylinder, cone, mesh), which the detector gets wrong on unseen objects (a dome called a sphere,
a tapered tower a cylinder): a class is then evidence, not proof, and pairing detections of
different classes costs :data:`CLASS_MISMATCH_COST` on top of the colour cost. With a scene's own
detector (*identity mode*, :attr:`Observation.classes` given) a label is an object class of the
scene (:class:`~services.common.scene_models.ObjectClass`): the class is the object, so pairs
need equal labels (:data:`FORBIDDEN` otherwise) and the proxy kind comes from the class's shape.

:data:`CLASS_MISMATCH_COST` is ``COLOUR_GATE − ALIKE_COST`` = 3 − 1 = 2 colour units: added to
the colour cost, a mislabelled pair stays under the colour gate (3, :mod:`.matching`) only when
its colours look alike (colour cost below :data:`ALIKE_COST`), and it costs as much as a colour
difference twice the look-alike threshold, so a same-class partner that looks alike always
wins.

Appearance
----------
Colours (mean sRGB of the object's pixels) vary with shading from view to view, so they are
compared by chromaticity ``(R, G, B) / (R + G + B)``, which a change of brightness leaves
alone; the cost is the chromaticity distance over its scale, 0 when either colour is unknown.
A dark colour's chromaticity is noisy: an error ``δ`` in the mean colour's channels (render
noise, shading, the object's mask) moves it by about ``δ / S``, ``S = R + G + B``. So the scale
is :data:`COLOUR_SCALE` grown by that noise, ``√(COLOUR_SCALE² + (κ_c / min(S_a, S_b))²)``
(κ_c = :data:`DARK_NOISE`): measured between renders of one object (16 against 8 samples per
pixel, the general detector, 5 generated scenes), ``distance · S`` has a 95th percentile of
2–7 at every brightness, and a near-black object (``S`` ≈ 20) was seen 0.18 apart, the gap
between orange and yellow three times over, which cost the pair its partner. The scale grows
by 10 % at ``S`` = 150 and by 2.5 % at ``S`` = 300 (mid grey is 384).

Two boxes on one object
-----------------------
A general detector unsure of an object's shape may put two boxes of different classes on it (a
tower as both cylinder and cone). :func:`merge_duplicates` takes two detections of different
classes to be one object when their boxes overlap heavily — IoU ≥ :data:`DUPLICATE_IOU`, or the
smaller box lies at least :data:`DUPLICATE_INSIDE` inside the larger and has at least
:data:`DUPLICATE_AREA_RATIO` of its area — and keeps the more confident one. Two distinct
objects rarely do that: one standing in front of the other hides most of it, so the one behind
shows a smaller box. Same-class duplicates are the detector's non-maximum suppression's job.

Edge noise
----------
A detection's box edges are off by the detector's localisation error and by the quantisation of
the image it saw. Each edge gets the standard deviation (camera pixels)

.. math:: σ_e^2 = \\Bigl(\\frac{p}{\\sqrt{12}}\\Bigr)^2 + (κ s)^2,

``p`` the camera pixels per image pixel (:attr:`Observation.pixel_px`: a pixel's position is
uniform within it), ``s = √(w h)`` the box's size and κ = :data:`EDGE_NOISE_FRACTION` the
localisation error of a box regressor as a fraction of the box (YOLO-style heads regress edges
in units of the object's size, so their error grows with it; JPEG blocking and a photo's blur
move edges by a similar fraction). The done test (:mod:`.strategies`) uses it.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.contracts.detect import Detection
from services.common.geometry.scene import CameraSpec
from services.optimizer.geometry import FloatArray
from services.optimizer.proxies import ProxyKind, kind_of

__all__ = [
    "ALIKE_COST",
    "CLASS_MISMATCH_COST",
    "COLOUR_SCALE",
    "DARK_NOISE",
    "DUPLICATE_AREA_RATIO",
    "DUPLICATE_INSIDE",
    "DUPLICATE_IOU",
    "EDGE_NOISE_FRACTION",
    "FORBIDDEN",
    "Observation",
    "appearance_cost",
    "box_overlaps",
    "box_sizes",
    "chromaticity",
    "edge_sigma",
    "merge_duplicates",
]

COLOUR_SCALE: Final = 0.06
"""Chromaticity distance that costs 1 (about the gap between orange and yellow)."""

DARK_NOISE: Final = 4.0
"""κ_c: chromaticity error times the colour's channel sum ``R + G + B`` (0–255 scale) from
view to view (module docstring)."""

ALIKE_COST: Final = 1.0
"""Detections of one class whose colour cost is below this look alike."""

FORBIDDEN: Final = 1e9
"""Cost of pairing detections of different object classes (identity mode)."""

CLASS_MISMATCH_COST: Final = 2.0
"""Cost of pairing detections of different shape classes (general detector): the colour gate
(3) minus :data:`ALIKE_COST` (module docstring)."""

DUPLICATE_IOU: Final = 0.6
DUPLICATE_INSIDE: Final = 0.8
DUPLICATE_AREA_RATIO: Final = 0.5

EDGE_NOISE_FRACTION: Final = 0.02
"""κ: standard deviation of a detected box edge as a fraction of the box's size."""


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

    Compared and hashed by identity, so derived quantities can be cached per observation;
    :attr:`digest` keys caches by content instead (across requests, which build new objects).

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
    classes : mapping of str to ProxyKind, optional
        Identity mode: the proxy kind of every object class (module docstring); None when
        labels are shape classes.
    pixel_px : float
        Camera pixels per pixel of the image the detector saw (its quantisation step).
    """

    labels: tuple[str, ...]
    boxes: FloatArray
    colors: FloatArray
    confidence: FloatArray
    classes: Mapping[str, ProxyKind] | None = field(default=None, repr=False)
    pixel_px: float = 1.0

    def __len__(self) -> int:
        return len(self.labels)

    @functools.cached_property
    def digest(self) -> bytes:
        """A 16-byte digest of everything the observation holds (equal content, equal digest)."""
        h = hashlib.blake2b(digest_size=16)
        classes = None if self.classes is None else sorted(self.classes.items())
        h.update(repr((self.labels, classes, self.pixel_px)).encode())
        for values in (self.boxes, self.colors, self.confidence):
            array = np.ascontiguousarray(values, dtype=np.float64)
            h.update(repr(array.shape).encode())
            h.update(array.tobytes())
        return h.digest()

    @property
    def identity(self) -> bool:
        """Whether labels are object classes (pairs need equal labels)."""
        return self.classes is not None

    @property
    def kinds(self) -> NDArray[np.int_]:
        """:class:`~.proxies.ProxyKind` per detection: the class's shape in identity mode,
        else the shape the label names."""
        if self.classes is not None:
            classes = self.classes
            return np.array([classes[label] for label in self.labels], dtype=np.int_)
        return np.array([kind_of(label) for label in self.labels], dtype=np.int_)

    @property
    def mismatch_cost(self) -> float:
        """Cost of pairing two of this observation's labels that differ (module docstring)."""
        return FORBIDDEN if self.identity else CLASS_MISMATCH_COST

    @property
    def edge_sigma(self) -> FloatArray:
        """``(n,)`` standard deviation of each box edge, camera pixels (module docstring)."""
        return edge_sigma(self.boxes, self.pixel_px)

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
        classes: Mapping[str, ProxyKind] | None = None,
    ) -> Observation:
        """An observation from camera-pixel boxes ``(n, 4)`` and optional colours/confidences."""
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        n = len(b)
        if len(labels) != n:
            raise ValueError(f"{len(labels)} labels for {n} boxes")
        c = np.full((n, 3), np.nan) if colors is None else np.asarray(colors, dtype=np.float64)
        p = np.ones(n) if confidence is None else np.asarray(confidence, dtype=np.float64)
        return cls(tuple(labels), b, c.reshape(n, 3), p.reshape(n), classes)

    @classmethod
    def from_detections(
        cls,
        detections: Sequence[Detection],
        image_size: tuple[int, int],
        camera: CameraSpec,
        classes: Mapping[str, ProxyKind] | None = None,
    ) -> Observation:
        """Scale detections of an image of ``image_size`` (width, height) to camera pixels;
        ``classes`` as the attribute (every label must be one of them)."""
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
            classes=classes,
            pixel_px=max(sx, sy),
        )

    def subset(self, keep: ArrayLike) -> Observation:
        """The detections selected by a boolean mask or index array."""
        idx = np.arange(len(self))[np.asarray(keep)]
        return Observation(
            labels=tuple(self.labels[i] for i in idx),
            boxes=self.boxes[idx],
            colors=self.colors[idx],
            confidence=self.confidence[idx],
            classes=self.classes,
            pixel_px=self.pixel_px,
        )


def appearance_cost(
    labels_a: Sequence[str],
    colors_a: ArrayLike,
    labels_b: Sequence[str],
    colors_b: ArrayLike,
    mismatch: float = CLASS_MISMATCH_COST,
) -> FloatArray:
    """``(n, m)`` cost of pairing detections: the chromaticity distance over its scale, grown
    for dark colours (module docstring; 0 when a colour is unknown), plus ``mismatch`` across
    classes (:data:`CLASS_MISMATCH_COST` for shape classes, :data:`FORBIDDEN` for object
    classes)."""
    la = np.asarray(labels_a, dtype=object).reshape(-1, 1)
    lb = np.asarray(labels_b, dtype=object).reshape(1, -1)
    same = la == lb
    rgb_a = np.asarray(colors_a, dtype=np.float64).reshape(-1, 3)
    rgb_b = np.asarray(colors_b, dtype=np.float64).reshape(-1, 3)
    ca = chromaticity(rgb_a)[:, np.newaxis, :]
    cb = chromaticity(rgb_b)[np.newaxis, :, :]
    darker = np.minimum(rgb_a.sum(axis=1)[:, np.newaxis], rgb_b.sum(axis=1)[np.newaxis, :])
    scale = np.hypot(COLOUR_SCALE, DARK_NOISE / np.maximum(darker, 1.0))
    distance = np.sqrt(np.sum((ca - cb) ** 2, axis=-1)) / scale
    colour = np.where(np.isnan(distance), 0.0, distance)
    if mismatch >= FORBIDDEN:
        return np.where(same, colour, FORBIDDEN)
    return np.where(same, colour, colour + mismatch)


def box_sizes(boxes: ArrayLike) -> FloatArray:
    """``(...)`` size ``√(w h)`` of boxes ``(..., 4)``, pixels."""
    b = np.asarray(boxes, dtype=np.float64)
    area = np.maximum(b[..., 2] - b[..., 0], 0.0) * np.maximum(b[..., 3] - b[..., 1], 0.0)
    sizes: FloatArray = np.sqrt(area)
    return sizes


def edge_sigma(boxes: ArrayLike, pixel_px: float = 1.0) -> FloatArray:
    """``(...)`` standard deviation of a detected box's edges, camera pixels: quantisation of
    pixels ``pixel_px`` wide and :data:`EDGE_NOISE_FRACTION` of the box's size, in quadrature
    (module docstring)."""
    quantisation = pixel_px / math.sqrt(12.0)
    sigma: FloatArray = np.hypot(quantisation, EDGE_NOISE_FRACTION * box_sizes(boxes))
    return sigma


def box_overlaps(boxes: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(n, n)`` IoU, intersection over the smaller box's area, and smaller over larger area."""
    lo = np.maximum(boxes[:, np.newaxis, :2], boxes[np.newaxis, :, :2])
    hi = np.minimum(boxes[:, np.newaxis, 2:], boxes[np.newaxis, :, 2:])
    inter = np.prod(np.maximum(hi - lo, 0.0), axis=-1)
    area = np.prod(np.maximum(boxes[:, 2:] - boxes[:, :2], 0.0), axis=-1)
    small = np.minimum(area[:, np.newaxis], area[np.newaxis, :])
    large = np.maximum(area[:, np.newaxis], area[np.newaxis, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.nan_to_num(inter / (area[:, np.newaxis] + area[np.newaxis, :] - inter))
        inside = np.nan_to_num(inter / small)
        ratio = np.nan_to_num(small / large)
    return iou, inside, ratio


def merge_duplicates(observation: Observation) -> tuple[Observation, tuple[str, ...]]:
    """Drop detections that are a second box of another class on a more confident detection's
    object (module docstring); returns the kept detections and one note per dropped one.

    Detections are taken most confident first; each is dropped when it overlaps an already
    kept detection of another class that much.
    """
    n = len(observation)
    if n < 2:
        return observation, ()
    iou, inside, ratio = box_overlaps(observation.boxes)
    same_object = (iou >= DUPLICATE_IOU) | (
        (inside >= DUPLICATE_INSIDE) & (ratio >= DUPLICATE_AREA_RATIO)
    )
    labels = observation.labels
    kept: list[int] = []
    notes: list[str] = []
    for i in np.argsort(-observation.confidence, kind="stable").tolist():
        over = [k for k in kept if labels[k] != labels[i] and same_object[i, k]]
        if not over:
            kept.append(i)
            continue
        k = over[0]
        notes.append(
            f"{labels[i]} ({observation.confidence[i]:.2f}) taken as a second box on "
            f"{labels[k]} ({observation.confidence[k]:.2f}): IoU {iou[i, k]:.2f}, "
            f"{inside[i, k]:.0%} of the smaller box inside the larger"
        )
    if len(kept) == n:
        return observation, ()
    return observation.subset(np.sort(np.array(kept, dtype=np.intp))), tuple(notes)
