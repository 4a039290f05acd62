"""Load a rendered dataset and turn samples into augmented training images (randomly scaled and
placed on the grey canvas; evaluation uses the detector service's letterbox)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from services.detector.letterbox import PAD_VALUE

__all__ = ["LabelledImage", "augment", "load_dataset"]

IGNORE_BELOW_VISIBLE = 0.6  # evaluation counts objects at least this visible


@dataclass
class LabelledImage:
    """An RGB image and its boxes (x1, y1, x2, y2 in pixels), classes and visible fractions."""

    rgb: NDArray[np.uint8]
    boxes: NDArray[np.float32]
    classes: NDArray[np.int64]
    visible: NDArray[np.float32]
    scene: str


def _u8(image: Any) -> NDArray[np.uint8]:
    return np.ascontiguousarray(image, dtype=np.uint8)


def load_dataset(root: Path, limit: int | None = None) -> list[LabelledImage]:
    """Every finished sample under ``root`` (as written by :mod:`training.dataset`)."""
    samples = []
    for label in sorted((root / "labels").glob("*.json"))[:limit]:
        meta = json.loads(label.read_text())
        bgr = cv2.imread(str(root / meta["image"]), cv2.IMREAD_COLOR)
        if bgr is None:
            continue
        objects = meta["objects"]
        samples.append(
            LabelledImage(
                rgb=_u8(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)),
                boxes=np.array([o["box"] for o in objects], dtype=np.float32).reshape(-1, 4),
                classes=np.array([o["class_id"] for o in objects], dtype=np.int64),
                visible=np.array([o["visible_fraction"] for o in objects], dtype=np.float32),
                scene=meta["scene"],
            )
        )
    return samples


def augment(
    sample: LabelledImage, width: int, height: int, rng: np.random.Generator
) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.int64]]:
    """A randomly scaled, placed, flipped, recoloured and degraded letterbox of ``sample``.

    Degradations mirror what targets may suffer: JPEG compression, Gaussian pixel noise, blur.
    Boxes are moved with the image; boxes mostly cut off by the canvas are dropped.
    """
    h, w = sample.rgb.shape[:2]
    scale = min(width / w, height / h) * rng.uniform(0.7, 1.15)
    new_w, new_h = max(8, round(w * scale)), max(8, round(h * scale))
    resized = cv2.resize(sample.rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    off_x = int(rng.integers(min(0, width - new_w), max(0, width - new_w) + 1))
    off_y = int(rng.integers(min(0, height - new_h), max(0, height - new_h) + 1))
    canvas = np.full((height, width, 3), PAD_VALUE, dtype=np.uint8)
    sx0, sy0 = max(0, -off_x), max(0, -off_y)
    dx0, dy0 = max(0, off_x), max(0, off_y)
    cw, ch = min(new_w - sx0, width - dx0), min(new_h - sy0, height - dy0)
    canvas[dy0 : dy0 + ch, dx0 : dx0 + cw] = resized[sy0 : sy0 + ch, sx0 : sx0 + cw]

    sx, sy = new_w / w, new_h / h
    boxes = sample.boxes * np.array([sx, sy, sx, sy], dtype=np.float32)
    boxes += np.array([off_x, off_y, off_x, off_y], dtype=np.float32)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    boxes = np.clip(boxes, 0, [width, height, width, height]).astype(np.float32)
    kept_area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    keep = (
        (kept_area >= 0.4 * np.maximum(area, 1e-6))
        & (boxes[:, 2] - boxes[:, 0] >= 2)
        & (boxes[:, 3] - boxes[:, 1] >= 2)
    )
    boxes, classes = boxes[keep], sample.classes[keep]

    if rng.random() < 0.5:
        canvas = canvas[:, ::-1].copy()
        boxes = boxes[:, [2, 1, 0, 3]] * np.array([-1, 1, -1, 1], dtype=np.float32)
        boxes += np.array([width, 0, width, 0], dtype=np.float32)
    hsv = cv2.cvtColor(canvas, cv2.COLOR_RGB2HSV).astype(np.float32)
    hsv[..., 0] = (hsv[..., 0] + rng.uniform(-4, 4)) % 180
    hsv[..., 1] *= rng.uniform(0.6, 1.3)
    hsv[..., 2] *= rng.uniform(0.7, 1.3)
    canvas = _u8(cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2RGB))
    if rng.random() < 0.3:
        noisy = canvas.astype(np.float32) + rng.normal(0, rng.uniform(2, 9), canvas.shape)
        canvas = np.clip(noisy, 0, 255).astype(np.uint8)
    if rng.random() < 0.1:
        canvas = _u8(cv2.GaussianBlur(canvas, (3, 3), rng.uniform(0.3, 1.0)))
    if rng.random() < 0.3:
        quality = int(rng.integers(40, 96))
        ok, jpeg = cv2.imencode(".jpg", canvas[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        decoded = cv2.imdecode(jpeg, cv2.IMREAD_COLOR) if ok else None
        if decoded is not None:
            canvas = _u8(decoded[..., ::-1])
    return canvas, boxes, classes
