"""API keys: ``cosmos keys`` creates, lists and revokes them in the controller's database; only
their hashes are stored; the local key of ``cosmos up`` is made once and reused while valid;
clients take ``COSMOS_API_KEY`` before the key file."""

from __future__ import annotations

import sqlite3
import stat

import pytest

from cosmos import cli
from cosmos.cli import search
from services.controller.client import ControllerClient, ControllerError
from services.controller.keys import (
    KeyStore,
    client_key,
    hash_key,
    key_file,
    local_key,
    rooted,
)


@pytest.fixture
def url(tmp_path, monkeypatch) -> str:
    """The controller's database, named as the controller reads it."""
    database = f"sqlite:///{tmp_path}/db/controller.sqlite3"
    monkeypatch.setenv("COSMOS_CONTROLLER_DATABASE_URL", database)
    monkeypatch.delenv("COSMOS_API_KEY", raising=False)
    return database


def listed(capsys) -> dict[str, list[str]]:
    assert cli.main(["keys", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:4] == ["id", "name", "kind", "created"]
    return {line.split()[0]: line.split() for line in lines[1:]}


def test_cosmos_keys_create_list_revoke_round_trip(url, capsys):
    assert cli.main(["keys", "create", "--name", "alice"]) == 0
    out, err = capsys.readouterr()
    alice = out.strip()  # alone on stdout, for KEY=$(cosmos keys create)
    assert alice.startswith("cosmos_")
    assert len(alice) == len("cosmos_") + 43
    assert "shown only now" in err
    assert cli.main(["keys", "create", "--admin", "--name", "ops"]) == 0
    ops = capsys.readouterr().out.strip()

    keys = KeyStore(url)
    alice_id = keys.verify(alice).id
    ops_id = keys.verify(ops).id
    assert alice_id != ops_id
    rows = listed(capsys)
    assert rows[alice_id][1:3] == ["alice", "tenant"]
    assert rows[ops_id][1:3] == ["ops", "admin"]
    assert len(rows[alice_id]) == 5  # id, name, kind, date, time: not revoked
    assert alice not in "\n".join(" ".join(r) for r in rows.values())  # never the key itself

    assert cli.main(["keys", "revoke", alice_id]) == 0
    assert f"revoked key {alice_id} (alice)" in capsys.readouterr().out
    assert keys.verify(alice) is None
    assert keys.verify(ops) is not None
    rows = listed(capsys)
    assert len(rows[alice_id]) == 7  # and when it was revoked
    assert len(rows[ops_id]) == 5

    assert cli.main(["keys", "revoke", "nope"]) == 1
    assert "no key 'nope'" in capsys.readouterr().err
    keys.close()


def test_only_the_hash_of_a_key_is_stored(url):
    keys = KeyStore(url)
    record, key = keys.create("alice")
    keys.close()
    dump = "\n".join(sqlite3.connect(url.removeprefix("sqlite:///")).iterdump())
    assert key not in dump
    assert hash_key(key) in dump
    assert record.id in dump


def test_a_key_needs_a_name(url):
    keys = KeyStore(url)
    with pytest.raises(ValueError, match="name"):
        keys.create("  ")
    keys.close()


def test_the_local_key_is_made_once_and_reused_while_valid(url):
    first = local_key(url)
    path = key_file(url)
    assert path.read_text().strip() == first
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert local_key(url) == first
    keys = KeyStore(url)
    record = keys.verify(first)
    assert (record.name, record.admin) == ("local", True)
    keys.revoke(record.id)
    second = local_key(url)  # a revoked key is replaced
    assert second != first
    assert keys.verify(second) is not None
    assert [k.name for k in keys.all()] == ["local", "local"]
    keys.close()


def test_a_client_sends_cosmos_api_key_else_the_local_key(url):
    assert client_key(url, environ={}) is None
    local = local_key(url)
    assert client_key(url, environ={}) == local
    assert client_key(url, environ={"COSMOS_API_KEY": " cosmos_given "}) == "cosmos_given"
    assert client_key("sqlite:///:memory:", environ={}) is None
    with pytest.raises(ValueError, match="in-memory"):
        local_key("sqlite:///:memory:")


def test_a_relative_database_is_taken_from_the_root(tmp_path):
    assert rooted("sqlite:///data/c.db", tmp_path) == f"sqlite:///{tmp_path}/data/c.db"
    assert rooted("sqlite:////abs/c.db", tmp_path) == "sqlite:////abs/c.db"
    assert rooted("sqlite:///:memory:", tmp_path) == "sqlite:///:memory:"


def test_cosmos_search_sends_the_local_key(url, monkeypatch, tmp_path):
    """``cosmos search`` against a running controller: the key ``cosmos up`` left."""
    local = local_key(url)
    sent: list[str | None] = []

    class Refusing(ControllerClient):
        def submit(self, image, scene, **options):
            sent.append(self._http.headers.get("Authorization"))
            raise ControllerError("controller", 401, "refused in this test")

    monkeypatch.setattr(search, "ControllerClient", Refusing)
    image = tmp_path / "t.png"
    image.write_bytes(b"\x89PNG")
    assert cli.main(["search", str(image), "--scene", "demo"]) == 1
    assert sent == [f"Bearer {local}"]
