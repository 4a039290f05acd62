"""sRGB values decoded to linear RGB, where light adds up (IEC 61966-2-1)."""

from __future__ import annotations

import numpy as np

from services.optimizer.geometry import FloatArray

__all__ = ["linear"]


def linear(srgb: FloatArray) -> FloatArray:
    """sRGB values in [0, 1] as linear RGB: ``v / 12.92`` up to 0.04045, else
    ``((v + 0.055) / 1.055)^2.4``."""
    out: FloatArray = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return out
