"""``ControllerClient.submit`` waits out the controller's 429 and 503 refusals that carry
``Retry-After``, within its budget, through a real stack: a full body budget is waited out and
the search taken; a quota whose ``Retry-After`` lies beyond the budget, or a budget of 0, ends
at once with the controller's own detail, and so does any other refusal; ``cosmos search`` says
so in a sentence; the fault suite's load counts each refusal it waits out and stops waiting when
it is stopped. The image goes in pieces (``in_pieces``), which make up the image."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cosmos import cli
from cosmos.bench.faults.harness import Load
from cosmos.bench.target import Target
from cosmos.stack import Stack, local_stack
from services.common.client import in_pieces
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import GridIndex, PoseQuery
from services.controller.client import ControllerClient, ControllerError, retry_after_s
from services.controller.keys import KeyStore
from services.renderer.client import RendererClient

pytestmark = pytest.mark.slow

LIMIT = 1 << 20  # the controller's upload limit: its body budget holds two such bodies
WAIT_S = 1.5  # how long an upload waits for the budget before its 503


@dataclass(frozen=True)
class Rig:
    stack: Stack
    tenant: str
    """A key with the quota of one search a minute (the stack's own key is an admin's)."""
    target: bytes
    """A PPM view of the demo scene: larger than a small body, so it waits for a full budget."""


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    workdir = tmp_path_factory.mktemp("client")
    env = {
        "COSMOS_CONTROLLER_QUOTA_SEARCHES_PER_MINUTE": "1",
        "COSMOS_CONTROLLER_MAX_UPLOAD_BYTES": str(LIMIT),
        "COSMOS_CONTROLLER_BODY_BUDGET_BYTES": str(2 * LIMIT),
        "COSMOS_CONTROLLER_BODY_WAIT_S": str(WAIT_S),
    }
    with local_stack(workdir, env=env) as stack:
        keys = KeyStore(f"sqlite:///{workdir}/controller.sqlite3")
        _, tenant = keys.create("tenant")
        keys.close()
        with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
            png = renderer.render_png(RenderRequest(scene="demo", pose=PoseQuery(lat=3, lon=5)))
        pixels = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        ok, ppm = cv2.imencode(".ppm", pixels)
        assert ok
        assert LIMIT // 16 < len(ppm) < LIMIT // 2  # a large body, but two fit in the budget
        yield Rig(stack, tenant, ppm.tobytes())


def hold_upload(stack: Stack, key: str) -> socket.socket:
    """A keyed maximal upload with half its body sent: it holds LIMIT bytes of the budget until
    its socket is closed."""
    host, port = stack.controller.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=10)
    head = (
        f"POST /searches?scene=demo HTTP/1.1\r\nHost: test\r\nContent-Type: image/png\r\n"
        f"Authorization: Bearer {key}\r\nContent-Length: {LIMIT}\r\n\r\n"
    )
    sock.sendall(head.encode() + b"\0" * (LIMIT // 2))
    return sock


def at_quota(rig: Rig) -> None:
    """Make sure the tenant submitted a search within the last minute (its quota)."""
    with ControllerClient(rig.stack.controller, api_key=rig.tenant) as client:
        try:
            client.submit(rig.target, "demo", retry_budget_s=0, max_iterations=3)
        except ControllerError as exc:
            if exc.status != 429:
                raise


def test_a_full_body_budget_is_waited_out_and_the_search_taken(rig):
    waits: list[tuple[int, str, float]] = []
    refused = threading.Event()
    result: dict[str, object] = {}

    def heard(refusal: ControllerError, wait_s: float) -> None:
        waits.append((refusal.status, refusal.detail, wait_s))
        refused.set()

    def submit() -> None:
        with ControllerClient(rig.stack.controller, api_key=rig.stack.api_key) as client:
            try:
                result["search"] = client.submit(
                    rig.target, "demo", retry_budget_s=30.0, on_wait=heard, max_iterations=3
                )
            except Exception as exc:  # reported below
                result["error"] = exc

    with ExitStack() as stack:
        holders = [stack.enter_context(hold_upload(rig.stack, rig.stack.api_key)) for _ in "ab"]
        time.sleep(0.2)  # both admitted: the budget is full
        started = time.monotonic()
        submitting = threading.Thread(target=submit)
        submitting.start()
        assert refused.wait(WAIT_S + 5.0), result
        for holder in holders:
            holder.close()  # their bytes come free
    submitting.join(30.0)
    assert not submitting.is_alive()
    assert "error" not in result, result
    search = result["search"]
    assert search.scene == "demo"
    assert search.status in {"queued", "running"}
    (status, detail, wait_s), *_ = waits
    assert status == 503
    assert "try again shortly" in detail  # the body budget's own refusal
    assert wait_s == 2.0  # its Retry-After: ⌈1.5 s⌉
    assert time.monotonic() - started >= WAIT_S + wait_s - 0.1


def test_a_refusal_beyond_the_budget_ends_at_once_with_the_controllers_detail(rig):
    with ControllerClient(rig.stack.controller, api_key=rig.tenant) as client:
        taken = client.submit(rig.target, "demo", retry_budget_s=0, max_iterations=3)
        assert taken.status in {"queued", "running"}
        waits: list[float] = []
        for budget_s in (0.0, 5.0):  # the minute's quota asks for ~60 s: more than either
            started = time.monotonic()
            with pytest.raises(ControllerError) as refused:
                client.submit(
                    rig.target,
                    "demo",
                    retry_budget_s=budget_s,
                    on_wait=lambda _, s: waits.append(s),
                )
            assert time.monotonic() - started < 2.0
            assert refused.value.status == 429
            assert "searches in the last minute" in refused.value.detail
            assert refused.value.retry_after_s is not None
            assert refused.value.retry_after_s > budget_s
            assert refused.value.waited_s == 0.0
        assert waits == []


def test_other_refusals_are_not_asked_again(rig):
    with ControllerClient(rig.stack.controller, api_key=rig.stack.api_key) as client:
        started = time.monotonic()
        with pytest.raises(ControllerError) as refused:
            client.submit(rig.target, "no-such-scene", on_wait=lambda *_: pytest.fail("waited"))
        assert refused.value.status == 404
        assert time.monotonic() - started < 2.0
    with ControllerClient(rig.stack.controller, api_key="cosmos_not-a-key") as client:
        with pytest.raises(ControllerError) as refused:
            client.submit(rig.target, "demo", on_wait=lambda *_: pytest.fail("waited"))
        assert refused.value.status == 401


def test_cosmos_search_says_the_controller_did_not_take_the_search(
    rig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    at_quota(rig)
    image = tmp_path / "target.ppm"
    image.write_bytes(rig.target)
    monkeypatch.setenv("COSMOS_API_KEY", rig.tenant)
    argv = ["search", str(image), "--scene", "demo", "--url", rig.stack.controller]
    assert cli.main([*argv, "--retry-for", "3", "--out", str(tmp_path)]) == 1
    said = capsys.readouterr().err
    assert "cosmos: the controller did not take the search (429: your key submitted" in said
    assert "beyond --retry-for 3 s: try again later, or give --retry-for more seconds" in said


def test_the_fault_loads_refusals_are_the_clients_waits_and_stop_with_the_load(rig, catalog):
    at_quota(rig)
    truth = GridIndex(lat=3, lon=5)
    pose = catalog.get("demo").spec.search.grid().pose(truth)
    load = Load(
        rig.stack.controller,
        rig.tenant,
        [Target("demo", rig.target, truth, pose)],
        concurrency=1,
        refused_wait_s=0.3,  # the cap of each wait: the minute's Retry-After is far longer
        options={"max_iterations": 3},
    ).start()
    time.sleep(1.5)
    stopped = time.monotonic()
    (outcome,) = load.stop(drain_s=0.0)
    assert time.monotonic() - stopped < 1.0  # a wait in progress ends with the load
    assert outcome.search_id is None  # never taken: at its quota
    assert not outcome.submitted
    assert 3 <= outcome.refusals <= 6  # one per 0.3 s wait


def test_retry_after_reads_seconds_and_http_dates():
    from datetime import UTC, datetime

    now = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    assert retry_after_s("5") == 5.0
    assert retry_after_s(" 12 ") == 12.0
    assert retry_after_s("Fri, 02 Jan 2026 03:04:35 GMT", now) == 30.0
    assert retry_after_s("Fri, 02 Jan 2026 03:04:00 GMT", now) == 0.0  # past: at once
    assert retry_after_s(None) is None
    assert retry_after_s("soon") is None
    assert retry_after_s("-3") is None


@given(st.binary(max_size=5000), st.integers(1, 700))
def test_a_body_in_pieces_is_the_body_in_order_none_larger_than_asked(body, size):
    pieces = list(in_pieces(body, size))
    assert b"".join(pieces) == body
    assert all(0 < len(piece) <= size for piece in pieces)
