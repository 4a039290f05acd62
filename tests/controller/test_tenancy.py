"""The public API wants an API key: none, a wrong one or a revoked one is a 401 with
``WWW-Authenticate``; a key sees and cancels its own searches only (another tenant's is a 404),
an admin key everyone's; the OpenAPI schema says so; browsers of other origins are kept out
unless allowed; ``COSMOS_CONTROLLER_AUTH=off`` opens everything."""

from __future__ import annotations

import json

import pytest
from sse_starlette import ServerSentEvent
from starlette.requests import Request

from cosmos import cli
from services.controller.api import health_events
from tests.controller.clients import key_client, key_id, new_key
from tests.controller.test_api import png_bytes, record

pytestmark = pytest.mark.anyio

SEARCH_ROUTES = [
    ("GET", "/searches/{id}"),
    ("GET", "/searches/{id}/events"),
    ("GET", "/searches/{id}/trajectory.png"),
    ("GET", "/searches/{id}/distance.png"),
    ("DELETE", "/searches/{id}"),
]


@pytest.fixture
def held(controller, monkeypatch):
    """The controller, with a runner that is told nothing: submitted searches stay queued."""
    app, _ = controller
    state = app.state.controller
    monkeypatch.setattr(
        state.runner,
        "submit",
        lambda search_id, recorded=None, leased=False: state.stages.forget_early(search_id),
    )
    return controller


async def submit(client) -> str:
    response = await client.post(
        "/searches", files={"image": ("t.png", png_bytes(), "image/png")}, data={"scene": "demo"}
    )
    assert response.status_code == 202, response.text
    return str(response.json()["id"])


async def test_two_tenants_cannot_see_or_cancel_each_others_searches(held):
    app, alice = held
    async with key_client(app, new_key(app, "bob")) as bob:
        mine = await submit(alice)
        theirs = await submit(bob)
        assert [s["id"] for s in (await alice.get("/searches")).json()["items"]] == [mine]
        page = (await bob.get("/searches")).json()
        assert (page["total"], [s["id"] for s in page["items"]]) == (1, [theirs])
        unknown = await bob.get("/searches/nope")
        for method, path in SEARCH_ROUTES:
            response = await bob.request(method, path.format(id=mine))
            assert response.status_code == 404, (method, path, response.text)
            assert response.headers["content-type"] == "application/problem+json"
            # as an unknown id: nothing tells another tenant's search from none
            assert response.json()["type"] == unknown.json()["type"]
            assert response.json()["title"] == unknown.json()["title"]
        assert (await alice.get(f"/searches/{mine}")).json()["status"] == "queued"  # not cancelled
        assert (await alice.get(f"/searches/{theirs}")).status_code == 404
        assert (await alice.get(f"/searches/{mine}")).status_code == 200


async def test_an_admin_key_sees_and_cancels_everyones_searches(held):
    app, tenant = held
    mine = await submit(tenant)
    state = app.state.controller
    record(state.store, "before-keys", "succeeded")  # from a controller without keys: no owner
    async with key_client(app, new_key(app, "ops", admin=True)) as admin:
        page = (await admin.get("/searches")).json()
        assert {s["id"] for s in page["items"]} == {mine, "before-keys"}
        assert (await admin.get(f"/searches/{mine}")).status_code == 200
        cancelled = await admin.delete(f"/searches/{mine}")
        assert cancelled.status_code == 200, cancelled.text
        assert cancelled.json()["status"] == "cancelled"
    assert (await tenant.get(f"/searches/{mine}")).json()["status"] == "cancelled"
    assert (await tenant.get("/searches/before-keys")).status_code == 404


@pytest.mark.parametrize(
    ("authorization", "error"),
    [
        (None, False),
        ("Basic dXNlcjpwYXNz", False),
        ("Bearer", False),
        ("Bearer cosmos_not-a-key", True),
    ],
)
async def test_no_key_or_a_wrong_one_is_a_401_that_says_what_to_do(
    controller, authorization, error
):
    app, _ = controller
    headers = {"Authorization": authorization} if authorization else None
    async with key_client(app, None) as anonymous:
        for method, path in [("GET", "/searches"), ("POST", "/searches"), ("GET", "/scenes")]:
            response = await anonymous.request(method, path, headers=headers)
            assert response.status_code == 401, (path, response.text)
            assert response.headers["content-type"] == "application/problem+json"
            challenge = response.headers["www-authenticate"]
            assert challenge.startswith("Bearer ")
            assert ('error="invalid_token"' in challenge) is error
            assert "cosmos keys create" in response.json()["detail"]
        for method, path in SEARCH_ROUTES:
            response = await anonymous.request(method, path.format(id="x"), headers=headers)
            assert response.status_code == 401, (method, path)
        health = await anonymous.get("/health")
        assert health.status_code == 200  # open: health checks carry no key


async def test_a_revoked_key_is_refused_from_its_next_request(controller, tmp_path, capsys):
    app, client = controller
    assert (await client.get("/searches")).status_code == 200
    # revoked by the command, on the database the running controller uses
    url = f"sqlite:///{tmp_path / 'controller.sqlite3'}"
    assert cli.main(["keys", "revoke", key_id(app, client), "--database-url", url]) == 0
    assert "revoked key" in capsys.readouterr().out
    response = await client.get("/searches")
    assert response.status_code == 401
    assert 'error="invalid_token"' in response.headers["www-authenticate"]


async def test_with_auth_off_everyone_sees_every_search(start_controller):
    async with start_controller(controller_auth=False) as (app, _):
        record(app.state.controller.store, "someones", "succeeded", owner="k1")
        async with key_client(app, None) as anonymous:
            page = await anonymous.get("/searches")
            assert page.status_code == 200
            assert [s["id"] for s in page.json()["items"]] == ["someones"]
            assert (await anonymous.get("/searches/someones")).status_code == 200


async def test_the_openapi_schema_declares_the_bearer_scheme_on_the_protected_routes(controller):
    _, client = controller
    schema = (await client.get("/openapi.json")).json()
    scheme = schema["components"]["securitySchemes"]["ApiKey"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    operations = {
        (method.upper(), path): operation
        for path, item in schema["paths"].items()
        for method, operation in item.items()
    }
    # health (and its events), probes
    open_routes = {
        ("GET", "/health"),
        ("GET", "/health/events"),
        ("GET", "/livez"),
        ("GET", "/readyz"),
    }
    for key in open_routes:
        assert operations[key].get("security") is None, key
    protected = {key for key in operations if key not in open_routes}
    assert len(protected) == 13  # with POST /searches/{id}/retry and the page's views
    for key in protected:
        assert operations[key]["security"] == [{"ApiKey": []}], key
        assert "401" in operations[key]["responses"], key
    assert "429" in operations[("POST", "/searches")]["responses"]


async def test_cors_is_closed_by_default(controller):
    _, client = controller
    response = await client.get("/searches", headers={"Origin": "https://elsewhere.example"})
    assert response.status_code == 200
    assert "access-control-allow-origin" not in response.headers
    preflight = await client.options(
        "/searches",
        headers={
            "Origin": "https://elsewhere.example",
            "Access-Control-Request-Method": "POST",
        },
    )
    assert "access-control-allow-origin" not in preflight.headers


async def test_cors_lets_the_configured_origins_in_only(start_controller):
    allowed = "https://app.example"
    async with start_controller(controller_cors_origins=f"{allowed}, http://localhost:5173") as (
        _,
        client,
    ):
        response = await client.get("/searches", headers={"Origin": allowed})
        assert response.headers["access-control-allow-origin"] == allowed
        assert "Retry-After" in response.headers["access-control-expose-headers"]
        preflight = await client.options(
            "/searches",
            headers={
                "Origin": allowed,
                "Access-Control-Request-Method": "POST",
                "Access-Control-Request-Headers": "authorization, content-type",
            },
        )
        assert preflight.status_code == 200
        assert preflight.headers["access-control-allow-origin"] == allowed
        assert "authorization" in preflight.headers["access-control-allow-headers"].lower()
        foreign = await client.get("/searches", headers={"Origin": "https://elsewhere.example"})
        assert "access-control-allow-origin" not in foreign.headers


def test_a_cors_setting_that_is_not_an_origin_is_refused():
    from pydantic import ValidationError

    from services.controller.settings import ControllerSettings

    with pytest.raises(ValidationError, match="not an origin"):
        ControllerSettings(controller_cors_origins="https://app.example/path")


STORE_FIGURES = ("store_searches", "store_image_bytes", "store_bytes")


async def health_event(app, client) -> dict:
    """The first ``health`` event of ``GET /health/events`` for ``client``'s key, read from the
    route's stream (the in-process transport would wait for the endless stream's end)."""
    headers = [(b"authorization", v.encode()) for v in client.headers.get_list("authorization")]
    request = Request(
        {"type": "http", "method": "GET", "path": "/health/events", "headers": headers}
    )
    response = await health_events(request, app.state.controller)
    stream = response.body_iterator
    try:
        chunk = await anext(stream)
    finally:
        await stream.aclose()  # type: ignore[attr-defined]
    assert isinstance(chunk, ServerSentEvent)
    assert chunk.event == "health"
    return json.loads(chunk.data)


async def test_the_open_health_shows_the_store_s_figures_to_an_admin_key_only(controller):
    """Whole-store counts (every tenant's) are not for anyone who asks: no key, a tenant's key
    or a wrong one gets the health without them, an admin key with them; the events alike."""
    app, tenant = controller
    record(app.state.controller.store, "someones", "succeeded", owner="k1")
    async with key_client(app, None) as anonymous, key_client(app, "cosmos_wrong") as wrong:
        for client in (anonymous, tenant, wrong):
            health = await client.get("/health")
            assert health.status_code == 200
            body = health.json()
            assert body["status"] == "ok" or body["unavailable_stages"]
            assert body["replicas"]  # the page's broker panel shows them
            for figure in STORE_FIGURES:
                assert body[figure] is None, (client.headers, figure)
                assert (await health_event(app, client))[figure] is None
    async with key_client(app, new_key(app, "ops", admin=True)) as admin:
        body = (await admin.get("/health")).json()
        assert body["store_searches"] == 1
        assert body["store_image_bytes"] == len(png_bytes())
        assert body["store_bytes"] > 0
        assert (await health_event(app, admin))["store_searches"] == 1
