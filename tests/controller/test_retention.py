"""What the store holds is bounded: finished searches expire with their images and iterations,
a failed search loses its image when it fails (unless an outage failed it: it may be retried),
the controller sweeps on its own, and ``/health`` says how much is held."""

from __future__ import annotations

import asyncio
import os
import sqlite3
from datetime import timedelta

import pytest

from services.common.contracts.search import OUTAGE
from services.common.errors import ProblemDetails
from services.controller.events import Notifier
from services.controller.runner import NotRetryable, SearchRunner
from services.controller.store import SearchStore, open_store, utcnow
from tests.controller.clients import key_client, key_id, new_key
from tests.controller.test_runner import PNG, FakeStages, run_stored
from tests.controller.test_runner import stored as stored_for_runner
from tests.controller.test_store import iteration, search

FAILED = ProblemDetails(title="Stage unavailable", status=503)


def rows(store: SearchStore, table: str) -> int:
    with store.database.read() as session:
        return int(session.execute(f"SELECT count(*) FROM {table}").fetchone()[0])


def test_finished_searches_expire_with_their_images_and_iterations(database_url, opened):
    store = opened()
    for name in ("done", "cancelled", "running", "queued"):
        store.create(search(name), b"\x89PNG-" + name.encode())
        store.add_iteration(name, iteration(0))
    store.update("done", status="succeeded")
    store.update("cancelled", status="cancelled")
    store.update("running", status="running")
    finished_at = utcnow()
    assert store.expire(finished_at - timedelta(seconds=60)) == 0  # not old enough yet
    assert store.expire(finished_at + timedelta(seconds=1)) == 2
    assert store.get("done") is None
    assert store.get("cancelled") is None
    with pytest.raises(KeyError):
        store.image("done")
    assert store.iterations("done") == []
    assert (rows(store, "searches"), rows(store, "images"), rows(store, "iterations")) == (2, 2, 2)
    # unfinished searches never expire, however old
    assert store.expire(finished_at + timedelta(days=365)) == 0
    assert set(store.unfinished()) == {"running", "queued"}
    store.close()


def test_a_search_expires_after_the_retention_time_from_when_it_finished(database_url, opened):
    store = opened()
    store.create(search("old", minutes=-60), b"x")  # created an hour ago, finished now
    store.update("old", status="succeeded")
    assert store.expire(utcnow() - timedelta(minutes=30)) == 0
    store.close()


def test_expiry_goes_in_batches(database_url, opened):
    store = opened()
    for n in range(7):
        store.create(search(f"s{n}"), b"x")
        store.update(f"s{n}", status="succeeded")
    assert store.expire(utcnow() + timedelta(seconds=1), batch=3) == 7
    assert rows(store, "searches") == 0
    store.close()


def test_a_failed_search_loses_its_image_and_keeps_its_record(database_url, opened):
    store = opened()
    store.create(search("a"), b"\x89PNG-a")
    store.update("a", status="failed", error=FAILED)
    with pytest.raises(KeyError):
        store.image("a")
    kept = store.get("a")
    assert kept is not None
    assert (kept.status, kept.error) == ("failed", FAILED)
    assert store.size().image_bytes == 0
    store.close()


def test_a_search_the_runner_fails_loses_its_image(tmp_path, detail):
    stages = FakeStages(detail, boxes=0)  # nothing in the target: the search fails
    store = stored_for_runner(tmp_path, stages)
    assert store.image("s1") == PNG
    final = run_stored(store, stages)
    assert final.status == "failed"
    assert final.error is not None
    with pytest.raises(KeyError):
        store.image("s1")
    store.close()


def test_the_store_reports_its_size(database_url, opened):
    store = opened()
    empty = store.size()
    assert (empty.searches, empty.image_bytes) == (0, 0)
    store.create(search("a"), os.urandom(50_000))  # random: PostgreSQL compresses the rest
    store.create(search("b"), os.urandom(20_000))
    size = store.size()
    assert (size.searches, size.image_bytes) == (2, 70_000)
    assert size.database_bytes - empty.database_bytes >= 70_000
    store.close()


def test_an_earlier_database_gets_owners_finish_times_and_image_sizes(tmp_path):
    """A database of the version before keys: its searches keep working, have no owner, expire
    from when they last changed, and its failed searches lose their images."""
    path = tmp_path / "old.sqlite3"
    old = sqlite3.connect(path)
    old.executescript(
        "CREATE TABLE searches (id TEXT PRIMARY KEY, status TEXT NOT NULL, "
        "created_at TEXT NOT NULL, doc TEXT NOT NULL);"
        "CREATE TABLE images (search_id TEXT PRIMARY KEY REFERENCES searches (id) "
        "ON DELETE CASCADE, image BLOB NOT NULL);"
        "CREATE TABLE iterations (search_id TEXT NOT NULL REFERENCES searches (id) "
        "ON DELETE CASCADE, idx INTEGER NOT NULL, doc TEXT NOT NULL, "
        "PRIMARY KEY (search_id, idx));"
    )
    for name, status, image in [("done", "succeeded", b"d" * 300), ("bad", "failed", b"b" * 200)]:
        record = search(name, minutes=-10).model_copy(update={"status": status})
        old.execute(
            "INSERT INTO searches VALUES (?, ?, ?, ?)",
            (name, status, record.created_at.isoformat(), record.model_dump_json()),
        )
        old.execute("INSERT INTO images VALUES (?, ?)", (name, image))
    old.commit()
    old.close()
    store = open_store(f"sqlite:///{path}")
    assert store.image("done") == b"d" * 300
    with pytest.raises(KeyError):
        store.image("bad")
    assert store.size().image_bytes == 300
    assert store.page(10, 0, visible_to="someone") == ([], 0)
    assert store.page(10, 0)[1] == 2
    assert store.expire(utcnow() - timedelta(minutes=11)) == 0
    assert store.expire(utcnow() - timedelta(minutes=9)) == 2  # finished 10 minutes ago
    store.close()
    open_store(f"sqlite:///{path}").close()  # opening it again changes nothing


@pytest.mark.anyio
async def test_the_controller_sweeps_expired_searches_and_health_reports_the_store(
    start_controller,
):
    async with start_controller(controller_retention_s=0.2, controller_retention_sweep_s=0.05) as (
        app,
        client,
    ):
        store = app.state.controller.store
        owner = key_id(app, client)
        store.create(search("running"), b"r" * 1000, owner=owner)
        store.update("running", status="running")
        store.create(search("done"), b"d" * 3000, owner=owner)
        store.update("done", status="succeeded")
        admin = key_client(app, new_key(app, "ops", admin=True))
        health = (await admin.get("/health")).json()  # the store's figures are an admin's
        assert (health["store_searches"], health["store_image_bytes"]) == (2, 4000)
        assert health["store_bytes"] > 4000
        for _ in range(100):
            if store.get("done") is None:
                break
            await asyncio.sleep(0.02)
        assert store.get("done") is None
        assert (await client.get("/searches/done")).status_code == 404
        health = (await admin.get("/health")).json()
        assert (health["store_searches"], health["store_image_bytes"]) == (1, 1000)
        await admin.aclose()


OUTAGE_ERROR = ProblemDetails(type=OUTAGE, title="No detector available", status=503)


def test_a_search_an_outage_failed_keeps_its_image_until_retried_or_expired(database_url, opened):
    """It may be retried (POST /searches/{id}/retry), which needs the image; queued again, it
    no longer counts as finished, so it does not expire while it runs."""
    store = opened()
    store.create(search("a"), b"\x89PNG-a")
    store.update("a", status="failed", error=OUTAGE_ERROR)
    assert store.image("a") == b"\x89PNG-a"
    assert store.holds_image("a")
    assert store.size().image_bytes == len(b"\x89PNG-a")
    reopened = store.reopen("a")
    assert (reopened.status, reopened.error) == ("queued", None)
    assert store.expire(utcnow() + timedelta(days=365)) == 0
    assert store.unfinished() == ["a"]
    store.update("a", status="failed", error=OUTAGE_ERROR)
    assert store.expire(utcnow() + timedelta(seconds=1)) == 1  # finished again: it expires
    store.close()


def test_a_search_that_lost_its_image_is_not_retried(tmp_path, detail):
    stages = FakeStages(detail)
    store = stored_for_runner(tmp_path, stages)
    store.update("s1", status="failed", error=OUTAGE_ERROR)
    runner = SearchRunner(store, stages, Notifier(), max_concurrent=1)  # type: ignore[arg-type]
    found = store.get("s1")
    assert found is not None
    assert runner.why_not_retryable(found) is None
    with store.database.write() as session:
        session.execute("DELETE FROM images WHERE search_id = 's1'")  # as an earlier version did
    why = runner.why_not_retryable(found)
    assert why is not None
    assert "no longer holds its target image" in why
    with pytest.raises(NotRetryable):
        runner.retry("s1")
    store.close()
