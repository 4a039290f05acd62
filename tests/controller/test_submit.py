"""Submitting large targets: an image over :data:`~services.controller.submit.INLINE_WRITE_BYTES`
is stored off the event loop, one insert at a time, and whole, by the controller app in process
(its body through the body bounds, as a real request's)."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest

from services.controller.submit import INLINE_WRITE_BYTES

pytestmark = pytest.mark.anyio


def noise_png(side: int, seed: int) -> bytes:
    """Random pixels: a PNG about ``3 * side**2`` bytes (they do not compress)."""
    pixels = np.random.default_rng(seed).integers(0, 256, (side, side, 3), np.uint8)
    ok, buffer = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    assert ok
    return buffer.tobytes()


async def test_large_targets_submitted_at_once_are_each_stored_whole(controller):
    app, client = controller
    images = [noise_png(720, seed) for seed in range(3)]
    assert all(len(image) > INLINE_WRITE_BYTES for image in images)
    answers = await asyncio.gather(
        *(
            client.post(
                "/searches",
                content=image,
                params={"scene": "demo", "seed": "1"},
                headers={"content-type": "image/png"},
            )
            for image in images
        )
    )
    assert [answer.status_code for answer in answers] == [202, 202, 202], answers[0].text
    store = app.state.controller.store
    for answer, image in zip(answers, images, strict=True):
        search = answer.json()
        assert search["target_size"] == [720, 720]
        assert store.image(search["id"]) == image
