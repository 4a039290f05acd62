"""The controller's store, on SQLite and PostgreSQL: what is written survives reopening, in
order; SQLite's own parts (databases from before the schema was versioned, checkpoints)."""

from __future__ import annotations

import sqlite3
import time
from datetime import timedelta

import pytest

from services.common.contracts.detect import Detection
from services.common.contracts.optimize import GridPose
from services.common.contracts.search import Iteration, Search, SearchResult, StageTimings
from services.common.errors import ProblemDetails
from services.common.geometry.pose import GridIndex, Pose
from services.controller.checkpoint import Checkpointer
from services.controller.store import (
    DatabaseUnavailable,
    database_path,
    open_store,
    utcnow,
)
from services.controller.store.migrations import MIGRATIONS

START = GridPose(index=GridIndex(lat=2, lon=3), theta_deg=22.5, phi_deg=60.0)


def search(search_id: str, minutes: int = 0) -> Search:
    when = utcnow() + timedelta(minutes=minutes)
    return Search(
        id=search_id,
        status="queued",
        scene="demo",
        strategy="reprojection",
        start=START,
        seed=1,
        max_iterations=10,
        created_at=when,
        updated_at=when,
        target_size=(320, 240),
    )


def iteration(index: int) -> Iteration:
    return Iteration(
        index=index,
        pose=START,
        image_size=(320, 240),
        detections=(),
        timings=StageTimings(render_ms=1.0, total_ms=2.0),
    )


def test_searches_iterations_and_results_survive_reopening(database_url, opened):
    store = opened()
    store.create(search("a"), b"\x89PNG-a")
    store.add_iteration("a", iteration(0))
    store.add_iteration("a", iteration(1))
    result = SearchResult(
        pose=START, refined_pose=Pose(theta_deg=22.4, phi_deg=60.2), confidence=0.9, renders=2
    )
    store.update("a", status="succeeded", result=result)
    store.close()

    again = opened()
    found = again.get("a")
    assert found is not None
    assert found.status == "succeeded"
    assert found.result == result
    assert [it.index for it in found.iterations] == [0, 1]
    assert again.image("a") == b"\x89PNG-a"
    assert found.updated_at >= found.created_at
    again.close()


def test_unfinished_searches_come_back_oldest_first(database_url, opened):
    store = opened()
    for name, minutes in [("late", 5), ("early", 1), ("done", 0), ("middle", 3)]:
        store.create(search(name, minutes), b"x")
    store.update("done", status="failed", error=ProblemDetails(title="x", status=422))
    store.update("middle", status="running")
    assert store.unfinished() == ["early", "middle", "late"]
    page, total = store.page(limit=2, offset=0)
    assert total == 4
    assert [s.id for s in page] == ["late", "middle"]


def test_a_resumed_iteration_replaces_its_earlier_record(database_url, opened):
    store = opened()
    store.create(search("a"), b"x")
    store.add_iteration("a", iteration(0))
    store.add_iteration("a", iteration(0).model_copy(update={"reason": "again"}))
    assert [it.reason for it in store.iterations("a")] == ["again"]


def test_unknown_searches_and_bad_urls(database_url, opened):
    store = opened()
    assert store.get("nope") is None
    with pytest.raises(KeyError):
        store.update("nope", status="running")
    with pytest.raises(ValueError, match="sqlite:///"):
        database_path("mysql://x")
    assert database_path("sqlite:///:memory:") == ":memory:"


def test_an_iteration_and_the_target_detections_are_recorded_together(database_url, opened):
    store = opened()
    store.create(search("a"), b"\x89PNG-a")
    seen = (Detection(label="sphere", class_id=0, confidence=0.9, box=(1.0, 2.0, 30.0, 40.0)),)
    store.add_iteration("a", iteration(0), target_detections=seen)
    found = store.get("a")
    assert found is not None
    assert found.target_detections == seen
    assert [it.index for it in found.iterations] == [0]
    # An iteration of an unknown search is refused whole, and the store carries on.
    with pytest.raises(KeyError):
        store.add_iteration("nope", iteration(0), target_detections=seen)
    assert store.iterations("nope") == []
    store.add_iteration("a", iteration(1))
    assert [it.index for it in store.iterations("a")] == [0, 1]
    store.close()


def test_the_last_iteration_and_the_result_are_recorded_together(database_url, opened):
    store = opened()
    store.create(search("a"), b"\x89PNG-a")
    store.add_iteration("a", iteration(0))
    assert store.status_doc("a") is not None
    assert store.status_doc("a")[0] == "queued"
    result = SearchResult(
        pose=START, refined_pose=Pose(theta_deg=22.0, phi_deg=61.0), confidence=0.9, renders=2
    )
    store.add_iteration("a", iteration(1), status="succeeded", result=result)
    status, doc = store.status_doc("a")
    assert status == "succeeded"
    assert Search.model_validate_json(doc).result == result
    # What the event stream sends: the stored documents, from an index on.
    assert [Iteration.model_validate_json(d) for d in store.iteration_docs("a", start=1)] == [
        iteration(1)
    ]
    assert store.iteration_docs("a", start=2) == []
    assert store.status_doc("nope") is None
    store.close()


def test_a_database_with_images_in_its_search_rows_is_moved_over(tmp_path):
    """An earlier version kept the target image in the search's row."""
    path = tmp_path / "old.sqlite3"
    old = sqlite3.connect(path)
    old.executescript(
        "CREATE TABLE searches (id TEXT PRIMARY KEY, status TEXT NOT NULL, "
        "created_at TEXT NOT NULL, doc TEXT NOT NULL, image BLOB NOT NULL);"
        "CREATE TABLE iterations (search_id TEXT NOT NULL REFERENCES searches (id) "
        "ON DELETE CASCADE, idx INTEGER NOT NULL, doc TEXT NOT NULL, "
        "PRIMARY KEY (search_id, idx));"
    )
    record = search("a")
    old.execute(
        "INSERT INTO searches VALUES (?, ?, ?, ?, ?)",
        ("a", "running", record.created_at.isoformat(), record.model_dump_json(), b"\x89PNG-a"),
    )
    old.execute("INSERT INTO iterations VALUES (?, ?, ?)", ("a", 0, iteration(0).model_dump_json()))
    old.commit()
    old.close()
    store = open_store(f"sqlite:///{path}")
    assert store.image("a") == b"\x89PNG-a"
    assert store.unfinished() == ["a"]
    assert [it.index for it in store.iterations("a")] == [0]
    store.add_iteration("a", iteration(1), status="succeeded")  # no image in the row any more
    store.close()
    columns = {row[1] for row in sqlite3.connect(path).execute("PRAGMA table_info(searches)")}
    assert "image" not in columns
    reopened = open_store(f"sqlite:///{path}")  # and opening it again changes nothing
    assert reopened.image("a") == b"\x89PNG-a"
    assert reopened.status_doc("a")[0] == "succeeded"
    reopened.close()


def _wal_bytes(db) -> int:
    wal = db.parent / f"{db.name}-wal"
    return wal.stat().st_size if wal.exists() else 0


def test_no_commit_copies_the_log_back(tmp_path):
    """Auto-checkpoints are off: 30 searches with 200 KB images (~1500 pages) grow the log past
    SQLite's 1000-page auto-checkpoint without any commit copying it back."""
    db = tmp_path / "c.sqlite3"
    store = open_store(f"sqlite:///{db}", checkpoint_every_s=3600)
    try:
        assert store.database.connection.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 0
        for n in range(30):
            store.create(search(f"s{n}"), bytes([n]) * 200_000)
        assert _wal_bytes(db) > 1000 * 4096
        busy, log, copied = store.database.checkpointer.checkpoint()
        assert busy == 0
        assert copied == log > 1000
    finally:
        store.close()
    assert _wal_bytes(db) == 0  # the last checkpoint empties the log
    reopened = open_store(f"sqlite:///{db}")
    try:
        assert reopened.image("s29") == bytes([29]) * 200_000
    finally:
        reopened.close()


def test_the_log_is_checkpointed_in_the_background(tmp_path):
    store = open_store(f"sqlite:///{tmp_path / 'c.sqlite3'}", checkpoint_every_s=0.02)
    try:
        store.create(search("a"), b"x" * 50_000)
        checkpointer = store.database.checkpointer
        for _ in range(500):
            if checkpointer.runs >= 2:
                break
            time.sleep(0.01)
        assert checkpointer.runs >= 2
        assert store.get("a") is not None  # the loop's connection reads on as before
    finally:
        store.close()


def test_memory_databases_have_no_checkpointer():
    store = open_store("sqlite:///:memory:")
    try:
        assert store.database.checkpointer is None
        store.create(search("a"), b"x")
        assert store.image("a") == b"x"
    finally:
        store.close()


def test_the_checkpoint_interval_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="every_s"):
        Checkpointer(str(tmp_path / "c.sqlite3"), every_s=0)


def test_the_schema_is_versioned_and_migrated_once(database_url, opened):
    store = opened()
    last = MIGRATIONS[-1].version
    assert [m.version for m in MIGRATIONS] == list(range(1, last + 1))
    with store.database.read() as session:
        versions = [row[0] for row in session.execute("SELECT version FROM schema_migrations")]
    assert sorted(versions) == list(range(1, last + 1))
    store.create(search("a"), b"x")
    again = opened()  # a second controller, or a restart: nothing applied again, nothing lost
    with again.database.read() as session:
        assert session.execute("SELECT count(*) FROM schema_migrations").fetchone()[0] == last
    assert again.image("a") == b"x"


def test_an_unreachable_postgresql_or_wrong_credentials_fail_in_one_line(postgres):
    with pytest.raises(DatabaseUnavailable) as wrong:
        open_store(postgres.url(password="not-the-password"))
    message = str(wrong.value)
    assert message.startswith("COSMOS_CONTROLLER_DATABASE_URL: PostgreSQL at 127.0.0.1:")
    assert "password authentication failed" in message
    assert "not-the-password" not in message
    assert "\n" not in message
    closed_port = postgres.port + 1 if postgres.port < 18699 else postgres.port - 1
    with pytest.raises(DatabaseUnavailable, match="COSMOS_CONTROLLER_DATABASE_URL.*refused"):
        open_store(f"postgresql://cosmos:x@127.0.0.1:{closed_port}/nope")
