"""Clients of an in-process controller that carry an API key, and the keys themselves."""

from __future__ import annotations

import httpx
from fastapi import FastAPI


def key_client(app: FastAPI, key: str | None) -> httpx.AsyncClient:
    """An in-process client of ``app`` that sends ``key`` (None: no Authorization header)."""
    headers = {"Authorization": f"Bearer {key}"} if key is not None else None
    return httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://controller", headers=headers
    )


def new_key(app: FastAPI, name: str, *, admin: bool = False) -> str:
    """A new key of the running controller ``app``."""
    _, key = app.state.controller.keys.create(name, admin=admin)
    return key


def key_id(app: FastAPI, client: httpx.AsyncClient) -> str:
    """The id of the key ``client`` sends (what owns the searches it submits)."""
    key = client.headers["Authorization"].removeprefix("Bearer ")
    record = app.state.controller.keys.verify(key)
    assert record is not None
    return str(record.id)
