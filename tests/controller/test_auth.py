"""Which requests the controller's key check refuses from the head (:mod:`services.controller.auth`,
in front of the body bounds) and which it leaves to the routes, through the app in process:
an upload to a route that wants a key, or to no route, is refused before its body is read; an
open route keeps its answers; the routes' own check says the same; no check with auth off."""

from __future__ import annotations

import pytest

from tests.controller.clients import key_client

pytestmark = pytest.mark.anyio

BODY = {"content": b"\x89PNG" + bytes(4096), "headers": {"content-type": "image/png"}}


async def test_an_upload_without_a_valid_key_is_refused_before_the_body_is_read(controller):
    app, client = controller
    for key in (None, "cosmos_unknown"):
        async with key_client(app, key) as stranger:
            for path in ("/searches?scene=demo", "/searches/x/retry", "/nowhere"):
                refused = await stranger.post(path, **BODY)
                assert refused.status_code == 401, (key, path)
                assert refused.headers["content-type"] == "application/problem+json"
                assert refused.headers["www-authenticate"].startswith('Bearer realm="cosmos"')
                assert refused.headers["connection"] == "close"  # its body was not read
            quiet = await stranger.post("/searches", headers={"content-length": "0"})
            assert quiet.status_code == 401  # no body: the route's own check
            assert "connection" not in quiet.headers
            assert quiet.json()["detail"] == refused.json()["detail"]  # one check, one answer
    assert (await client.post("/nowhere", **BODY)).status_code == 404  # a key: on to routing
    async with key_client(app, None) as stranger:
        assert (await stranger.post("/health", **BODY)).status_code == 405  # an open path
        assert (await stranger.post("/livez", **BODY)).status_code == 405


async def test_a_valid_key_or_auth_off_lets_an_upload_through(controller, start_controller):
    _, client = controller
    taken = await client.post("/searches?scene=nope", **BODY)
    assert taken.status_code == 415  # read and judged by the route: not an image
    async with start_controller(controller_auth=False) as (app, _):
        async with key_client(app, None) as anyone:
            assert (await anyone.post("/searches?scene=nope", **BODY)).status_code == 415
