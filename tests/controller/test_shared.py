"""Controllers sharing one PostgreSQL database: keys, quotas and retention hold across them
(two stores on one database are two controllers)."""

from __future__ import annotations

import asyncio
import time
from datetime import timedelta

import pytest

from services.controller.keys import KeyStore
from services.controller.quotas import Limits, QuotaExceededError, Quotas
from services.controller.store import open_database, utcnow
from tests.controller.clients import key_client
from tests.controller.test_quotas import submit
from tests.controller.test_store import iteration, search


def test_keys_hold_across_controllers(database_url):
    """On either back end: a key created through one store is verified, and once revoked
    refused, through another on the same database."""
    first, second = KeyStore(database_url), KeyStore(open_database(database_url))
    try:
        record, key = first.create("alice")
        assert second.verify(key) == record
        assert [k.id for k in second.all()] == [record.id]
        assert second.revoke(record.id).revoked_at is not None
        assert first.verify(key) is None
        assert first.get(record.id).revoked_at == second.get(record.id).revoked_at
        admin, admin_key = second.create("ops", admin=True)
        assert first.verify(admin_key).admin
    finally:
        first.close()
        second.close()
        second.database.close()


def test_quotas_and_retention_hold_across_controllers(postgres, opened):
    url = postgres.new_schema()
    one, other = opened(url), opened(url)
    limits = Limits(active_searches=2, searches_per_minute=99, stored_bytes=10**6, retention_s=60)
    for name in ("a", "b"):
        one.create(search(name), b"x" * 10, owner="k")
    with pytest.raises(QuotaExceededError) as refused:  # the other controller counts them
        Quotas(other, limits).check("k", 10)
    assert refused.value.extra["quota"] == "active_searches"
    other.update("a", status="succeeded")
    Quotas(one, limits).check("k", 10)  # a finished one no longer counts, on either
    assert one.expire(utcnow() + timedelta(seconds=1)) == 1  # expired by either
    assert other.get("a") is None
    assert other.expire(utcnow() + timedelta(seconds=1)) == 0


@pytest.mark.anyio
async def test_any_controller_answers_and_follows_a_search_another_runs(postgres, start_controller):
    """Two in-process controllers on one database: a search submitted to the first (which
    waits 1.5 s for a detector, then fails) is seen and followed to its end through the
    second, with the same key."""
    url = postgres.new_schema()
    async with (
        start_controller(controller_database_url=url, controller_outage_budget_s=1.5) as (
            first,
            client,
        ),
        start_controller(controller_database_url=url) as (second, _),
    ):
        key = client.headers["Authorization"].removeprefix("Bearer ")
        async with key_client(second, key) as other:
            submitted = await submit(client)
            assert submitted.status_code == 202, submitted.text
            search_id = submitted.json()["id"]
            seen = await other.get(f"/searches/{search_id}")
            assert seen.status_code == 200
            assert seen.json()["status"] in {"queued", "running"}
            events = await asyncio.wait_for(other.get(f"/searches/{search_id}/events"), 30)
            assert events.status_code == 200
            assert "event: end" in events.text
            assert (await other.get(f"/searches/{search_id}")).json()["status"] == "failed"
        with first.state.controller.store.database.read() as session:
            holder = session.execute("SELECT holder FROM leases").fetchone()[0]
        assert holder == first.state.controller.runner.leases.holder  # the first ran it


def test_changes_are_announced_to_every_listener_once_committed(postgres, opened):
    url = postgres.new_schema()
    writer, reader = opened(url), opened(url)
    heard: list[str | None] = []
    listener = reader.database.listen(heard.append)
    try:
        assert listener.connected.wait(10)
        writer.create(search("a"), b"x")
        with pytest.raises(KeyError):  # rolled back: nothing announced
            writer.update("nope", status="running")
        writer.add_iteration("a", iteration(0))
        deadline = time.monotonic() + 10
        while heard.count("a") < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        listener.close()
    assert heard == [None, "a", "a"]  # connected (changes may have been missed), then each write
