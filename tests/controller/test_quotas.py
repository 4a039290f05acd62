"""Quotas per key: searches queued or running at once, searches per minute, bytes of target
images held. Over one, ``POST /searches`` answers 429 with ``Retry-After`` and a problem detail
naming the quota and what to do; other keys, and admin keys, go on."""

from __future__ import annotations

from datetime import timedelta

import pytest

from services.common.contracts.search import SearchStatus
from services.controller.quotas import Limits, QuotaExceededError, Quotas
from services.controller.store import SearchStore, utcnow
from tests.controller.clients import key_client, key_id, new_key
from tests.controller.test_api import png_bytes
from tests.controller.test_store import search

pytestmark = pytest.mark.anyio


def hold(app, monkeypatch) -> None:
    """Submitted searches stay queued: the runner is told nothing."""
    state = app.state.controller
    monkeypatch.setattr(
        state.runner,
        "submit",
        lambda search_id, recorded=None, leased=False: state.stages.forget_early(search_id),
    )


def stored(
    store: SearchStore,
    search_id: str,
    owner: str,
    *,
    status: SearchStatus = "succeeded",
    image: bytes = b"x",
    minutes_ago: float = 0.0,
) -> None:
    """A search of ``owner`` created ``minutes_ago``, now in ``status``."""
    store.create(search(search_id, minutes=0), image, owner=owner)
    created = utcnow() - timedelta(minutes=minutes_ago)
    with store.database.write() as session:
        session.execute(
            "UPDATE searches SET created_at = ? WHERE id = ?",
            (store.database.stamp(created), search_id),
        )
    if status != "queued":
        store.update(search_id, status=status)


async def submit(client):
    return await client.post(
        "/searches", files={"image": ("t.png", png_bytes(), "image/png")}, data={"scene": "demo"}
    )


def assert_quota(response, quota: str, most_s: float) -> int:
    assert response.status_code == 429, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert problem["type"] == "urn:cosmos:problem:quota-exceeded"
    assert problem["quota"] == quota
    retry = int(response.headers["retry-after"])
    assert 1 <= retry <= most_s
    assert problem["retry_after_s"] == retry
    return retry


async def test_searches_queued_or_running_at_once(start_controller, monkeypatch):
    async with start_controller(controller_quota_active_searches=2) as (app, client):
        hold(app, monkeypatch)
        store = app.state.controller.store
        stored(store, "running", key_id(app, client), status="running")
        stored(store, "done", key_id(app, client), status="succeeded")  # not active
        assert (await submit(client)).status_code == 202
        refused = await submit(client)
        assert_quota(refused, "active_searches", 60)
        assert "cancel one (DELETE /searches/{id})" in refused.json()["detail"]
        async with key_client(app, new_key(app, "other")) as other:
            assert (await submit(other)).status_code == 202  # a quota is one key's
        async with key_client(app, new_key(app, "ops", admin=True)) as admin:
            for _ in range(3):
                assert (await submit(admin)).status_code == 202  # admin keys have none
        store.update("running", status="cancelled")
        assert (await submit(client)).status_code == 202  # room again


async def test_searches_per_minute(start_controller, monkeypatch):
    async with start_controller(controller_quota_searches_per_minute=3) as (app, client):
        hold(app, monkeypatch)
        store = app.state.controller.store
        owner = key_id(app, client)
        for n in range(3):
            stored(store, f"old{n}", owner, minutes_ago=1.5)  # outside the window
        stored(store, "a", owner, minutes_ago=0.5)
        assert (await submit(client)).status_code == 202
        stored(store, "b", owner, minutes_ago=0.2)
        refused = await submit(client)
        # the oldest of the minute's searches leaves the window in ~30 s
        retry = assert_quota(refused, "searches_per_minute", 31)
        assert retry >= 29
        assert "submit again after Retry-After seconds" in refused.json()["detail"]


async def test_stored_bytes(start_controller, monkeypatch):
    retention_s = 3600.0
    async with start_controller(
        controller_quota_stored_bytes=4096, controller_retention_s=retention_s
    ) as (app, client):
        hold(app, monkeypatch)
        store = app.state.controller.store
        owner = key_id(app, client)
        image = len(png_bytes())
        stored(store, "big", owner, image=b"x" * (4096 - image + 1))
        stored(store, "failed", owner, status="failed", image=b"x" * 4000)  # its image is gone
        refused = await submit(client)
        # "big" finished just now: its image goes with it after the retention time
        retry = assert_quota(refused, "stored_bytes", retention_s)
        assert retry >= retention_s - 60
        assert "bytes of target images" in refused.json()["detail"]
        store.update("big", status="failed")  # frees its image
        assert (await submit(client)).status_code == 202


async def test_an_image_larger_than_the_whole_quota_is_a_413(start_controller):
    async with start_controller(controller_quota_stored_bytes=1024) as (_, client):
        response = await client.post(
            "/searches",
            files={"image": ("t.png", png_bytes() + b"\0" * 2000, "image/png")},
            data={"scene": "demo"},
        )
        assert response.status_code == 413, response.text
        assert "storage quota" in response.json()["detail"]


def test_admissions_not_yet_recorded_count(database_url, opened):
    """Between admitting a search and recording it the route awaits; a burst of one key's
    submissions must not all pass the same check, whichever quota it would exceed."""
    store = opened()
    roomy = {"active_searches": 99, "searches_per_minute": 99, "stored_bytes": 10**6}
    for quota, tight in [
        ("active_searches", 2),
        ("searches_per_minute", 2),
        ("stored_bytes", 25),
    ]:
        quotas = Quotas(store, Limits(**{**roomy, quota: tight}, retention_s=1))
        with quotas.admit("k", 10), quotas.admit("k", 10):
            with pytest.raises(QuotaExceededError) as refused:
                quotas.check("k", 10)
            assert refused.value.extra["quota"] == quota
            quotas.check("other", 10)
        quotas.check("k", 10)  # both released
        assert quotas._pending == {}
    store.close()


async def test_a_tenant_frees_its_stored_bytes_by_deleting_its_searches(
    start_controller, monkeypatch
):
    """DELETE cancels a queued search (it keeps its image: still counted); a second DELETE
    deletes it with its image and iterations, and its bytes no longer count. Another tenant
    cannot delete it (404, as an unknown id); an admin key can."""
    room = len(png_bytes()) * 3 // 2  # one image, not two
    async with start_controller(controller_quota_stored_bytes=1024) as (app, client):
        hold(app, monkeypatch)
        store = app.state.controller.store
        stored(store, "old", key_id(app, client), image=b"x" * (1024 - room))
        first = (await submit(client)).json()["id"]
        cancelled = await client.delete(f"/searches/{first}")
        assert cancelled.status_code == 200, cancelled.text
        assert cancelled.json()["status"] == "cancelled"
        assert_quota(await submit(client), "stored_bytes", 7 * 24 * 3600)
        async with key_client(app, new_key(app, "other")) as other:
            assert (await other.delete(f"/searches/{first}")).status_code == 404
        assert store.holds_image(first)
        deleted = await client.delete(f"/searches/{first}")
        assert deleted.status_code == 204, deleted.text
        assert (await client.get(f"/searches/{first}")).status_code == 404
        assert (await client.delete(f"/searches/{first}")).status_code == 404
        assert not store.holds_image(first)
        assert store.iterations(first) == []
        second = await submit(client)
        assert second.status_code == 202, second.text  # room again

        search_id = second.json()["id"]
        store.update(search_id, status="succeeded")
        async with key_client(app, new_key(app, "ops", admin=True)) as admin:
            assert (await admin.delete(f"/searches/{search_id}")).status_code == 204
        assert store.get(search_id) is None


async def test_deleting_searches_does_not_lift_the_searches_per_minute(
    start_controller, monkeypatch
):
    async with start_controller(controller_quota_searches_per_minute=2) as (app, client):
        hold(app, monkeypatch)
        for _ in range(2):
            search_id = (await submit(client)).json()["id"]
            for answer in (200, 204):  # cancelled, then deleted
                assert (await client.delete(f"/searches/{search_id}")).status_code == answer
        assert_quota(await submit(client), "searches_per_minute", 61)
