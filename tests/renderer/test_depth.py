"""The depth archive: what POST /render/depth answers, read back, and garbage refused."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.depth import DepthImage


def test_a_depth_archive_reads_back_exactly():
    rng = np.random.default_rng(0)
    image = DepthImage(
        depth=rng.uniform(0.0, 9.0, (6, 8)).astype(np.float32),
        objects=rng.integers(-1, 5, (6, 8)).astype(np.int16),
    )
    again = DepthImage.from_npz(image.npz())
    assert np.array_equal(again.depth, image.depth)
    assert np.array_equal(again.objects, image.objects)


@pytest.mark.parametrize("data", [b"", b"garbage", b"PK\x03\x04not a zip"])
def test_anything_else_is_refused(data):
    with pytest.raises(ValueError, match=r"pickled|depth archive"):
        DepthImage.from_npz(data)


def test_arrays_of_two_shapes_are_refused():
    mismatched = DepthImage(
        depth=np.zeros((4, 4), np.float32), objects=np.zeros((4, 5), np.int16)
    ).npz()
    with pytest.raises(ValueError, match="one shape"):
        DepthImage.from_npz(mismatched)


def test_the_outline_shading_reads_back_and_a_misshapen_one_is_refused():
    depth, objects = np.ones((4, 6), np.float32), np.zeros((4, 6), np.int16)
    shading = np.arange(24, dtype=np.uint8).reshape(4, 6)
    again = DepthImage.from_npz(DepthImage(depth, objects, shading=shading).npz())
    assert again.shading is not None
    assert np.array_equal(again.shading, shading)
    assert DepthImage.from_npz(DepthImage(depth, objects).npz()).shading is None
    wrong = DepthImage(depth, objects, shading=np.zeros((4, 5), np.uint8)).npz()
    with pytest.raises(ValueError, match="shading"):
        DepthImage.from_npz(wrong)
