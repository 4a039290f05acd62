"""The one value-noise generator (:mod:`scene_assets.noise`): seeded, in range, smooth, and the
same numbers the committed textures and the seeded scene generators were made from."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scene_assets import value_noise


@pytest.mark.parametrize(("low", "high", "octaves"), [(0.0, 1.0, 1), (-1.0, 1.0, 1), (0.0, 1.0, 4)])
def test_noise_is_seeded_and_in_range(low, high, octaves):
    def noise(seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        return value_noise(rng, (64, 48), (4, 3), octaves=octaves, low=low, high=high)

    a, b = noise(3), noise(3)
    assert a.shape == (64, 48)
    assert a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert a.min() >= low
    assert a.max() <= high
    assert a.std() > 0.05 * (high - low)
    other = value_noise(
        np.random.default_rng(4), (64, 48), (4, 3), octaves=octaves, low=low, high=high
    )
    assert not np.array_equal(a, other)


def test_noise_is_smooth_at_its_cell_size():
    """Neighbouring pixels differ far less than the samples do: the grid is upsampled, not
    repeated."""
    noise = value_noise(np.random.default_rng(0), (256, 256), (8, 8))
    assert np.abs(np.diff(noise, axis=0)).max() < 0.1
    assert np.abs(np.diff(noise, axis=1)).max() < 0.1


def test_one_octave_is_the_upsampled_sample_grid():
    """The definition: one octave is the bicubic upsampling of one draw of the grid, clipped; the
    generator is left where that draw leaves it."""
    rng, reference = np.random.default_rng(11), np.random.default_rng(11)
    noise = value_noise(rng, (100, 80), (5, 4))
    grid = reference.random((5, 4)).astype(np.float32)
    expected = cv2.resize(grid, (80, 100), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    np.testing.assert_array_equal(noise, expected)
    assert rng.random() == reference.random()


def test_octaves_halve_in_amplitude_and_double_in_cells():
    rng, reference = np.random.default_rng(5), np.random.default_rng(5)
    noise = value_noise(rng, (64, 64), (4, 4), octaves=3)
    total = np.zeros((64, 64), np.float32)
    for o in range(3):
        grid = reference.random((4 * 2**o, 4 * 2**o)).astype(np.float32)
        total += 0.5**o * cv2.resize(grid, (64, 64), interpolation=cv2.INTER_CUBIC)
    np.testing.assert_array_equal(noise, np.clip(total / 1.75, 0.0, 1.0))


def test_octaves_must_be_positive():
    with pytest.raises(ValueError, match="octaves"):
        value_noise(np.random.default_rng(0), (8, 8), (2, 2), octaves=0)
