"""Turn the renderer's linear radiance into 8-bit sRGB images and PNG bytes."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["encode_png", "linear_to_srgb8"]


def linear_to_srgb8(linear: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Linear RGB (any float array, clipped to [0, 1]) to 8-bit sRGB with the IEC 61966-2-1 curve:
    ``12.92 c`` below 0.0031308, else ``1.055 c^(1/2.4) - 0.055``."""
    c = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    out: NDArray[np.uint8] = (srgb * 255.0 + 0.5).astype(np.uint8)
    return out


def encode_png(rgb: NDArray[np.uint8], compression: int = 1) -> bytes:
    """PNG bytes of an RGB ``(H, W, 3)`` image; low zlib compression favours speed."""
    ok, buffer = cv2.imencode(
        ".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, compression]
    )
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(buffer)
