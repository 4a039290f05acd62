"""Value noise for procedural textures: the one noise generator.

A grid of uniform random samples, bicubically upsampled to the image (OpenCV ``INTER_CUBIC``),
summed over octaves whose grids double in cells and whose amplitudes halve, then clipped to the
samples' range. The same generator state gives the same array, so seeded textures are
reproducible byte for byte (the committed ``scenes/textures`` depend on it).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["value_noise"]


def value_noise(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cells: tuple[int, int],
    *,
    octaves: int = 1,
    low: float = 0.0,
    high: float = 1.0,
) -> NDArray[np.float32]:
    """Value noise of ``shape`` (rows, columns), float32 in [``low``, ``high``].

    .. math:: n(x) = \\operatorname{clip}\\Big(\\sum_{o<O} 2^{-o}\\, C_o(x) \\Big/
              \\sum_{o<O} 2^{-o},\\ \\mathrm{low},\\ \\mathrm{high}\\Big)

    where :math:`C_o` is the bicubic upsampling of a ``cells · 2^o`` grid of samples drawn
    uniformly from [``low``, ``high``) (one draw of the grid per octave, in octave order).

    Parameters
    ----------
    rng : the generator the samples are drawn from.
    shape : (rows, columns) of the result, pixels.
    cells : (rows, columns) of the first octave's sample grid.
    octaves : how many octaves are summed (:math:`O`), at least 1.
    low, high : the samples' range, and the range the result is clipped to.
    """
    if octaves < 1:
        raise ValueError(f"octaves must be at least 1, not {octaves}")
    total = np.zeros(shape, np.float32)
    weight = 0.0
    for o in range(octaves):
        grid_shape = (cells[0] * 2**o, cells[1] * 2**o)
        grid = rng.uniform(low, high, size=grid_shape).astype(np.float32)
        total += 0.5**o * cv2.resize(grid, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
        weight += 0.5**o
    noise: NDArray[np.float32] = np.clip(total / weight, low, high)
    return noise
