"""Letterbox geometry: golden sizes and paddings, pixel-exact content placement, exact inverse."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.detector.letterbox import PAD_VALUE, fit, letterbox


@pytest.mark.parametrize(
    ("image", "net", "resized", "pad"),
    [
        ((640, 360), (320, 320), (320, 180), (0, 70)),  # wide: rows of padding on top and bottom
        ((200, 400), (320, 320), (160, 320), (80, 0)),  # tall: columns left and right
        ((320, 240), (320, 256), (320, 240), (0, 8)),  # the renderer's film, no resize
        ((320, 240), (320, 320), (320, 240), (0, 40)),
        ((333, 207), (320, 320), (320, 199), (0, 60)),  # odd padding: the extra row goes below
        ((100, 100), (320, 256), (256, 256), (32, 0)),  # upscaled
        ((5000, 1), (320, 320), (320, 1), (0, 159)),  # degenerate strip keeps one row
    ],
)
def test_fit_golden(image, net, resized, pad):
    box = fit(image, net)
    assert box.resized_size == resized
    assert box.pad == pad


def test_fit_rejects_empty_sizes():
    with pytest.raises(ValueError, match="positive"):
        fit((0, 10), (320, 320))


@pytest.mark.parametrize(
    ("image", "net", "input_box", "image_box"),
    [
        # 640x360 -> scale 0.5, 70 rows of padding on top
        ((640, 360), (320, 320), (80, 90, 120, 170), (160, 40, 240, 200)),
        # 200x400 -> scale 0.8, 80 columns of padding on the left
        ((200, 400), (320, 320), (96, 40, 144, 200), (20, 50, 80, 250)),
        # 320x240 -> scale 1, 8 rows of padding on top
        ((320, 240), (320, 256), (10, 8, 20, 248), (10, 0, 20, 240)),
    ],
)
def test_boxes_map_back_exactly(image, net, input_box, image_box):
    box = fit(image, net)
    assert tuple(box.to_image(np.array(input_box))) == image_box
    assert tuple(box.to_input(np.array(image_box))) == input_box


def test_to_image_clips_to_the_image():
    box = fit((640, 360), (320, 320))
    clipped = box.to_image(np.array([[-10.0, 0.0, 400.0, 330.0]]))
    assert clipped.tolist() == [[0.0, 0.0, 640.0, 360.0]]
    raw = box.to_image(np.array([[-10.0, 0.0, 400.0, 330.0]]), clip=False)
    assert raw.tolist() == [[-20.0, -140.0, 800.0, 520.0]]


@pytest.mark.parametrize(
    ("image", "net", "rect"),
    [
        ((640, 360), (320, 320), (160, 40, 240, 200)),
        ((200, 400), (320, 320), (20, 50, 80, 250)),
        ((320, 240), (320, 256), (13, 7, 101, 99)),
        ((100, 80), (320, 320), (10, 20, 30, 50)),  # upscaled by 3.2
    ],
)
def test_content_lands_where_the_mapping_says(image, net, rect):
    """A white rectangle drawn at ``rect`` (image pixels) shows up in the network input exactly
    at ``to_input(rect)``: the forward transform and its inverse agree with the pixels."""
    w, h = image
    rgb = np.zeros((h, w, 3), dtype=np.uint8)
    x1, y1, x2, y2 = rect
    rgb[y1:y2, x1:x2] = 255
    tensor, box = letterbox(rgb, net)
    assert tensor.shape == (3, net[1], net[0])
    assert tensor.dtype == np.float32
    ys, xs = np.nonzero(tensor[0] > 0.5)
    found = (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    np.testing.assert_allclose(found, box.to_input(np.array(rect)), atol=0.5)
    back = box.to_image(np.array(found, dtype=float))
    np.testing.assert_allclose(back, rect, atol=0.5 / min(box.scale))


def test_padding_is_grey_114_and_channels_are_rgb():
    rgb = np.zeros((360, 640, 3), dtype=np.uint8)
    rgb[..., 0] = 255  # pure red
    tensor, box = letterbox(rgb, (320, 320))
    assert box.pad == (0, 70)
    pad_value = np.float32(PAD_VALUE) / np.float32(255.0)
    assert np.all(tensor[:, :70] == pad_value)
    assert np.all(tensor[:, 250:] == pad_value)
    assert np.all(tensor[0, 70:250] == 1.0)
    assert np.all(tensor[1:, 70:250] == 0.0)


def test_letterbox_rejects_non_rgb_arrays():
    with pytest.raises(ValueError, match="uint8"):
        letterbox(np.zeros((10, 10), dtype=np.uint8), (32, 32))


sizes = st.tuples(st.integers(1, 4000), st.integers(1, 4000))
net_sizes = st.tuples(st.integers(16, 1280), st.integers(16, 1280))


@given(image=sizes, net=net_sizes, data=st.data())
@settings(max_examples=300, deadline=None)
def test_map_then_unmap_is_identity(image, net, data):
    box = fit(image, net)
    w, h = image
    xs = sorted(data.draw(st.lists(st.floats(0, w), min_size=2, max_size=2)))
    ys = sorted(data.draw(st.lists(st.floats(0, h), min_size=2, max_size=2)))
    corners = np.array([xs[0], ys[0], xs[1], ys[1]])
    back = box.to_image(box.to_input(corners), clip=False)
    np.testing.assert_allclose(back, corners, rtol=0, atol=1e-6)
    # the image lands inside the input, centred (the odd pixel of padding goes right/below)
    (new_w, new_h), (pad_x, pad_y) = box.resized_size, box.pad
    assert 1 <= new_w <= net[0]
    assert 1 <= new_h <= net[1]
    assert 0 <= (net[0] - new_w) - 2 * pad_x <= 1
    assert 0 <= (net[1] - new_h) - 2 * pad_y <= 1
    # and fills it along at least one axis (up to rounding)
    assert new_w == net[0] or new_h == net[1] or min(new_w, new_h) == 1
    mapped = box.to_input(np.array([0.0, 0.0, w, h]))
    np.testing.assert_allclose(mapped, [pad_x, pad_y, pad_x + new_w, pad_y + new_h], atol=1e-9)
