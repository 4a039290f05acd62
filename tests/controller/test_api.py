"""The controller app in process over an in-process renderer: a scene whose grid the optimizer
cannot search is refused at submission with a 422 naming the field, followers of a search's
events leave nothing behind in the notifier, and a finished search's plots are drawn once."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest

from services.common.base import MAX_SAFE_INTEGER
from services.common.contracts.optimize import GridPose
from services.common.contracts.search import Search, SearchStatus
from services.common.geometry.pose import GridIndex
from services.controller.events import Notifier
from services.controller.plots import PlotCache
from services.controller.store import SearchStore, utcnow
from tests.controller.clients import key_id

pytestmark = pytest.mark.anyio


def png_bytes() -> bytes:
    ok, buffer = cv2.imencode(".png", np.zeros((24, 32, 3), np.uint8))
    assert ok
    return bytes(buffer)


async def test_a_grid_the_optimizer_cannot_search_is_refused_at_submission(controller):
    _, client = controller
    response = await client.post(
        "/searches", files={"image": ("t.png", png_bytes(), "image/png")}, data={"scene": "fine"}
    )
    assert response.status_code == 422, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    problem = response.json()
    assert problem["type"] == "urn:cosmos:problem:unsupported-grid"
    assert problem["field"] == "search.angle_step_deg"
    assert "fine" in problem["detail"]
    listed = await client.get("/searches")
    assert listed.status_code == 200
    assert listed.json()["total"] == 0  # nothing was recorded


def record(
    store: SearchStore,
    search_id: str,
    status: SearchStatus,
    scene: str = "demo",
    *,
    owner: str | None = None,
) -> None:
    """Store a search as if ``owner`` submitted it (the runner is not told, so it stays as
    stored)."""
    now = utcnow()
    search = Search(
        id=search_id,
        status=status,
        scene=scene,
        strategy="reprojection",
        start=GridPose(index=GridIndex(lat=3, lon=0), theta_deg=30.0, phi_deg=0.0),
        seed=1,
        max_iterations=5,
        created_at=now,
        updated_at=now,
        target_size=(32, 24),
    )
    store.create(search, png_bytes(), owner=owner)


async def test_the_trajectory_of_a_search_whose_grid_became_unsearchable_is_a_422(controller):
    """A search taken before its scene file changed to a grid the optimizer cannot search."""
    app, client = controller
    record(app.state.controller.store, "old", "cancelled", scene="fine", owner=key_id(app, client))
    response = await client.get("/searches/old/trajectory.png")
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "search.angle_step_deg"


async def test_followers_that_come_and_go_leave_nothing_in_the_notifier(controller):
    """Followers of a finished search, and followers of a running one that disconnect (their
    request is cancelled while they wait), leave no event behind."""
    app, client = controller
    state = app.state.controller
    owner = key_id(app, client)
    record(state.store, "finished", "cancelled", owner=owner)
    record(state.store, "running", "running", owner=owner)
    for _ in range(5):
        response = await client.get("/searches/finished/events")
        assert response.status_code == 200
        assert response.text.startswith("event: end")
    for _ in range(5):
        with pytest.raises(TimeoutError):  # the client gives up; the app's stream is cancelled
            await asyncio.wait_for(client.get("/searches/running/events"), timeout=0.05)
    assert state.notifier._events == {}
    assert state.notifier.followed() == 0


async def test_a_follower_wakes_on_a_change_and_then_lets_go():
    notifier = Notifier()
    with notifier.following("s"):
        changed = notifier.current("s")
        assert notifier.followed() == 1
        notifier.publish("s")
        assert changed.is_set()
        assert notifier.current("s") is not changed  # the next change sets a fresh event
    assert notifier.followed() == 0


async def test_a_finished_search_s_plots_are_drawn_once_a_running_one_s_every_time(controller):
    app, client = controller
    state = app.state.controller
    owner = key_id(app, client)
    record(state.store, "done", "cancelled", owner=owner)
    record(state.store, "running", "running", owner=owner)
    for name in ("trajectory.png", "distance.png"):
        first = await client.get(f"/searches/done/{name}")
        second = await client.get(f"/searches/done/{name}")
        assert first.status_code == second.status_code == 200
        assert first.content == second.content
    assert state.plots.hits == 2
    assert len(state.plots) == 2
    for _ in range(2):
        assert (await client.get("/searches/running/distance.png")).status_code == 200
    assert state.plots.hits == 2  # drawn each time, not kept
    assert len(state.plots) == 2
    state.store.update("done", status="failed")  # changed since (as a retried search would be)
    assert (await client.get("/searches/done/distance.png")).status_code == 200
    assert state.plots.hits == 2
    assert len(state.plots) == 3


async def test_the_plot_cache_keeps_the_most_recently_used():
    cache = PlotCache(capacity=2)
    drawn: list[str] = []

    def search(search_id: str) -> Search:
        now = utcnow()
        return Search(
            id=search_id,
            status="succeeded",
            scene="demo",
            strategy="reprojection",
            start=GridPose(index=GridIndex(lat=3, lon=0), theta_deg=30.0, phi_deg=0.0),
            seed=1,
            max_iterations=5,
            created_at=now,
            updated_at=now,
            target_size=(32, 24),
        )

    def drawing(search_id: str):
        async def draw() -> bytes:
            drawn.append(search_id)
            return search_id.encode()

        return draw

    a, b, c = search("a"), search("b"), search("c")
    for s in (a, b, a, c, a, b):  # c pushes out b (a was used since); b comes back
        assert await cache.png(s, "distance", drawing(s.id)) == s.id.encode()
    assert drawn == ["a", "b", "c", "b"]
    assert cache.hits == 2
    assert len(cache) == 2


async def test_the_largest_offset_a_page_takes_is_one_its_answer_can_carry(controller):
    _, client = controller
    largest = await client.get("/searches", params={"offset": MAX_SAFE_INTEGER})
    assert largest.status_code == 200, largest.text
    assert largest.json()["offset"] == MAX_SAFE_INTEGER
    beyond = await client.get("/searches", params={"offset": MAX_SAFE_INTEGER + 1})
    assert beyond.status_code == 422
    assert beyond.json()["field"] == "offset"
