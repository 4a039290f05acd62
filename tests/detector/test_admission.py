"""The decode budget: bytes held never exceed it, waiters are served in arrival order, and a
waiter that times out or is cancelled leaves nothing behind."""

from __future__ import annotations

import asyncio

import pytest

from services.common.errors import PayloadTooLargeError, ServiceUnavailableError
from services.common.images import ImageHeader
from services.detector.admission import DecodeBudget

pytestmark = pytest.mark.anyio


def image(megabytes: int) -> ImageHeader:
    """A header whose decode holds ``megabytes`` MB (an 8-bit RGB image 1000 pixels wide)."""
    return ImageHeader("png", 1000, megabytes * 1000 // 3 or 1, channels=3)


async def test_requests_wait_in_arrival_order_and_never_exceed_the_budget():
    budget = DecodeBudget(limit_bytes=10_000_000, wait_s=5.0)
    order: list[str] = []
    held: list[int] = []

    async def request(name: str, megabytes: int, work_s: float) -> None:
        async with budget.hold(image(megabytes)):
            order.append(name)
            held.append(budget.in_use)
            await asyncio.sleep(work_s)

    first = asyncio.create_task(request("big-1", 6, 0.05))
    await asyncio.sleep(0)
    rest = [
        asyncio.create_task(request(name, size, 0.01))
        for name, size in [("big-2", 6), ("small-1", 1), ("small-2", 1)]
    ]
    await asyncio.gather(first, *rest)
    # small-1 would fit beside big-1, but big-2 came first: no overtaking.
    assert order == ["big-1", "big-2", "small-1", "small-2"]
    assert max(held) <= budget.limit_bytes
    assert budget.peak == max(held)
    assert budget.in_use == 0


async def test_a_request_that_cannot_get_its_bytes_in_time_gets_503_and_leaves_the_queue():
    budget = DecodeBudget(limit_bytes=10_000_000, wait_s=0.05)
    release = asyncio.Event()

    async def holder() -> None:
        async with budget.hold(image(9)):
            await release.wait()

    task = asyncio.create_task(holder())
    await asyncio.sleep(0)
    with pytest.raises(ServiceUnavailableError, match="COSMOS_DETECTOR_MAX_DECODE_BYTES"):
        async with budget.hold(image(2)):
            pass
    release.set()
    await task
    assert budget.in_use == 0
    async with budget.hold(image(10)):  # nothing left queued in front
        assert budget.in_use == image(10).decoded_bytes


async def test_an_image_larger_than_the_budget_is_413():
    budget = DecodeBudget(limit_bytes=1_000_000, wait_s=1.0)
    header = ImageHeader("png", 4096, 4096, channels=4, bit_depth=16)
    with pytest.raises(PayloadTooLargeError, match="134217728 bytes"):
        async with budget.hold(header):
            pass
    assert budget.in_use == 0


async def test_a_cancelled_waiter_leaves_nothing_behind():
    budget = DecodeBudget(limit_bytes=10_000_000, wait_s=5.0)
    release = asyncio.Event()

    async def holder(megabytes: int) -> None:
        async with budget.hold(image(megabytes)):
            await release.wait()

    first = asyncio.create_task(holder(8))
    await asyncio.sleep(0)
    waiter = asyncio.create_task(holder(8))
    behind = asyncio.create_task(holder(1))
    await asyncio.sleep(0.01)
    waiter.cancel()
    await asyncio.sleep(0.01)
    # With the cancelled waiter gone, the small one behind it fits beside the first.
    assert budget.in_use == image(8).decoded_bytes + image(1).decoded_bytes
    release.set()
    await asyncio.gather(first, behind)
    with pytest.raises(asyncio.CancelledError):
        await waiter
    assert budget.in_use == 0
