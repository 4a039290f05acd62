"""Submitting large targets: an image over :data:`~services.controller.submit.INLINE_WRITE_BYTES`
is stored off the event loop, one insert at a time, and whole, by the controller app in process
(its body through the body bounds, as a real request's); a submission cancelled while its image
is being stored leaves no search behind."""

from __future__ import annotations

import asyncio
import logging
import sqlite3

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


async def test_a_submission_cancelled_while_its_large_image_is_stored_leaves_no_search(
    controller, tmp_path, caplog
):
    """The image's write runs on a thread, which a cancelled request cannot stop: the search it
    commits must not stay behind, queued, unknown to the runner until a restart. Another
    connection holds the database's write lock (as ``cosmos keys create`` may), so the write is
    under way, waiting, when the request is cancelled; then the lock is let go."""
    app, client = controller
    store = app.state.controller.store
    image = noise_png(720, seed=7)
    assert len(image) > INLINE_WRITE_BYTES
    other = sqlite3.connect(tmp_path / "controller.sqlite3", isolation_level=None)
    caplog.set_level(logging.INFO, logger="cosmos.controller")
    try:
        other.execute("BEGIN IMMEDIATE")  # the write lock: the store's insert waits for it
        submitting = asyncio.create_task(
            client.post(
                "/searches",
                content=image,
                params={"scene": "demo"},
                headers={"content-type": "image/png"},
            )
        )
        await asyncio.sleep(1.0)  # decoded, and the insert waiting (for up to 5 s)
        assert not submitting.done()
        submitting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await submitting
    finally:
        other.execute("COMMIT")
        other.close()
    for _ in range(100):  # the write commits now, then is undone
        if "discarded search" in caplog.text:
            break
        await asyncio.sleep(0.05)
    assert store.page(10, 0)[1] == 0  # no search queued that the runner was never told of
    assert app.state.controller.runner.queued == 0
    assert "its submission was cancelled while it was stored" in caplog.text  # it was written
