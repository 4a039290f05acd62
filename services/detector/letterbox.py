"""Letterboxing: fit an image into the network's fixed input, and map boxes back exactly.

Geometry (Ultralytics' ``LetterBox`` with ``center=True``, which YOLO training uses). An image of
``w x h`` pixels goes into an input of ``W x H``:

- gain ``r = min(W / w, H / h)``; the resized image is ``w' x h'`` with ``w' = max(1, round(w r))``
  and ``h' = max(1, round(h r))`` (cv2.INTER_LINEAR);
- it is centred: ``pad_x = (W - w') // 2`` columns of grey 114 on the left (the odd column, if
  any, goes right) and ``pad_y = (H - h') // 2`` rows on top;
- channels are RGB, values ``/ 255`` in [0, 1], layout ``3 x H x W``.

Coordinates are pixel *edges* (the left edge of column 0 is x = 0, its right edge x = 1). OpenCV's
resize maps the edge at ``x`` to ``x * w' / w`` exactly, so with the per-axis scales
``s_x = w' / w`` and ``s_y = h' / h`` (equal to ``r`` up to the rounding of ``w'`` and ``h'``):

    x_in = pad_x + s_x x        x = (x_in - pad_x) / s_x
    y_in = pad_y + s_y y        y = (y_in - pad_y) / s_y

Ultralytics' ``scale_boxes`` uses ``r`` for both axes and a padding recomputed from it, which can
be off by up to half a pixel of the input; here the inverse is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["PAD_VALUE", "Letterbox", "fit", "letterbox"]

PAD_VALUE = 114
"""Grey level (0-255, all channels) of the padding, as in YOLO training."""


@dataclass(frozen=True)
class Letterbox:
    """Where an image of ``image_size`` lands inside an input of ``input_size`` (both (w, h))."""

    image_size: tuple[int, int]
    input_size: tuple[int, int]
    resized_size: tuple[int, int]
    pad: tuple[int, int]
    """Columns on the left and rows on top, in input pixels."""

    @property
    def _pad(self) -> NDArray[np.float64]:
        return np.array([*self.pad, *self.pad], dtype=np.float64)

    @property
    def _image(self) -> NDArray[np.float64]:
        return np.array([*self.image_size, *self.image_size], dtype=np.float64)

    @property
    def _resized(self) -> NDArray[np.float64]:
        return np.array([*self.resized_size, *self.resized_size], dtype=np.float64)

    @property
    def scale(self) -> tuple[float, float]:
        """``(s_x, s_y)``: input pixels per image pixel along each axis."""
        return (
            self.resized_size[0] / self.image_size[0],
            self.resized_size[1] / self.image_size[1],
        )

    def to_input(self, boxes: NDArray[np.floating]) -> NDArray[np.float64]:
        """Boxes ``(..., 4)`` as ``x1, y1, x2, y2`` in image pixels -> input pixels."""
        out: NDArray[np.float64] = (
            np.asarray(boxes, dtype=np.float64) * self._resized / self._image + self._pad
        )
        return out

    def to_image(self, boxes: NDArray[np.floating], *, clip: bool = True) -> NDArray[np.float64]:
        """Boxes ``(..., 4)`` as ``x1, y1, x2, y2`` in input pixels -> image pixels, clipped to
        the image ``[0, w] x [0, h]`` unless ``clip`` is false."""
        # multiply before dividing: exact whenever the true answer is a representable number
        out: NDArray[np.float64] = (
            (np.asarray(boxes, dtype=np.float64) - self._pad) * self._image / self._resized
        )
        if clip:
            w, h = self.image_size
            np.clip(out, 0.0, np.array([w, h, w, h], dtype=np.float64), out=out)
        return out


def fit(image_size: tuple[int, int], input_size: tuple[int, int]) -> Letterbox:
    """The letterbox geometry of an image of ``image_size`` in an input of ``input_size``."""
    (w, h), (in_w, in_h) = image_size, input_size
    if min(w, h, in_w, in_h) < 1:
        raise ValueError(f"sizes must be positive, got image {image_size} and input {input_size}")
    gain = min(in_w / w, in_h / h)
    new_w = min(in_w, max(1, round(w * gain)))
    new_h = min(in_h, max(1, round(h * gain)))
    return Letterbox(
        image_size=(w, h),
        input_size=(in_w, in_h),
        resized_size=(new_w, new_h),
        pad=((in_w - new_w) // 2, (in_h - new_h) // 2),
    )


def letterbox(
    rgb: NDArray[np.uint8], input_size: tuple[int, int]
) -> tuple[NDArray[np.float32], Letterbox]:
    """The network input for an RGB ``(h, w, 3)`` uint8 image: a ``(3, H, W)`` float32 tensor in
    [0, 1] (RGB, grey padding), and the geometry to map boxes back."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (h, w, 3) uint8 image, got {rgb.shape} {rgb.dtype}")
    box = fit((rgb.shape[1], rgb.shape[0]), input_size)
    resized = rgb
    if box.resized_size != box.image_size:
        resized = np.asarray(
            cv2.resize(rgb, box.resized_size, interpolation=cv2.INTER_LINEAR), dtype=np.uint8
        )
    in_w, in_h = input_size
    canvas = np.full((in_h, in_w, 3), PAD_VALUE, dtype=np.uint8)
    (px, py), (new_w, new_h) = box.pad, box.resized_size
    canvas[py : py + new_h, px : px + new_w] = resized
    tensor = np.empty((3, in_h, in_w), dtype=np.float32)
    np.divide(canvas.transpose(2, 0, 1), np.float32(255.0), out=tensor)
    return tensor, box
