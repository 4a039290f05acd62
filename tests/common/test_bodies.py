"""Request bodies bounded by bytes in flight and by time (:mod:`services.common.bodies`): the
budget's arithmetic, and its behaviour through a real controller process over raw sockets (a
request waits, then is admitted; waits too long, 503 with ``Retry-After``, the rest of its body
read and dropped so the connection is not reset; a trickling body, 408 and its bytes released;
small requests and GETs do not wait; an upload without a valid API key is refused before its
body is admitted or read)."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Iterator
from contextlib import ExitStack

import pytest

from cosmos.launch import ServiceProcess, free_port, running_service
from services.common.bodies import LINGER_IDLE_S, BodyBudget, BodyLimits
from services.controller.keys import KeyStore

MIB = 1 << 20
LIMIT = 1 * MIB  # the upload limit of the process below: its budget holds two of these
WAIT_S = 1.5
TIMEOUT_S = 1.5
RATE = 1 * MIB  # so a maximal body has TIMEOUT_S + 1 s to arrive
KEY: dict[str, str] = {}
"""The API key of the controller process below (``key``), made before it starts."""


# -- the arithmetic -----------------------------------------------------------------------------


def test_the_defaults_hold_four_maximal_bodies_and_give_large_bodies_time_by_size():
    limits = BodyLimits.for_limit(20 * MIB)
    assert limits.budget_bytes == 80 * MIB
    assert limits.small_bytes == 20 * MIB // 16
    assert limits.deadline_s(20 * MIB) == pytest.approx(10.0 + 20 * MIB / (512 * 1024))
    assert limits.deadline_s(None) == limits.deadline_s(20 * MIB)  # streamed: the most it may be
    assert limits.deadline_s(0) == 10.0
    assert BodyLimits(20 * MIB).budget() is None  # no budget unless asked for
    with pytest.raises(ValueError, match="cannot hold one body"):
        BodyLimits(20 * MIB, budget_bytes=10 * MIB)


@pytest.mark.anyio
async def test_large_bodies_queue_in_order_while_small_ones_have_a_lane_of_their_own():
    budget = BodyBudget(limit_bytes=100, small_bytes=10, wait_s=0.5)
    first, second = await budget.acquire(60), await budget.acquire(40)
    assert first is not None
    assert second is not None
    assert budget.in_use == 100
    waiting = asyncio.create_task(budget.acquire(50))
    await asyncio.sleep(0.01)
    assert budget.waiting == 1
    # A small body is not held up by the large ones, up to its lane of 100 / 4.
    smalls = [await budget.acquire(10), await budget.acquire(10)]
    assert all(smalls)
    assert budget.in_use == 120
    first.release()  # 60 free: the waiting 50 gets them
    third = await waiting
    assert third is not None
    assert budget.in_use == 40 + 50 + 20
    assert await budget.acquire(10) is None  # the small lane is full (25): it waited 0.5 s
    # Nothing overtakes a waiting large body, not even one that would fit.
    second.release()
    blocked = asyncio.create_task(budget.acquire(60))
    await asyncio.sleep(0.01)
    later = asyncio.create_task(budget.acquire(20))  # 50 + 20 fits, but 60 came first
    await asyncio.sleep(0.01)
    assert not later.done()
    assert budget.waiting == 2
    third.shrink(20)  # a streamed body gives back what it did not use: 20 of its 50 held
    assert (await blocked) is not None
    assert (await later) is not None
    assert budget.in_use == 20 + 60 + 20 + 20
    assert budget.peak >= budget.in_use


# -- through a real process ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def controller(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A controller whose budget holds two bodies of its 1 MiB limit (small: 64 KiB), waits 1.5 s
    and gives a maximal body 2.5 s to arrive, with an API key (:data:`KEY`). No stage runs
    (their addresses are free ports): the requests below, with the key, are refused once
    admitted and read (:func:`handled`), which is what they test."""
    directory = tmp_path_factory.mktemp("bodies")
    database = f"sqlite:///{directory}/controller.sqlite3"
    keys = KeyStore(database)
    _, KEY["key"] = keys.create("bodies")
    keys.close()
    env = {
        "COSMOS_CONTROLLER_DATABASE_URL": database,
        **{
            f"COSMOS_CONTROLLER_{stage}_URLS": f"http://127.0.0.1:{free_port()}"
            for stage in ("RENDERER", "DETECTOR", "OPTIMIZER")
        },
        "COSMOS_CONTROLLER_MAX_UPLOAD_BYTES": str(LIMIT),
        "COSMOS_CONTROLLER_BODY_BUDGET_BYTES": str(2 * LIMIT),
        "COSMOS_CONTROLLER_BODY_WAIT_S": str(WAIT_S),
        "COSMOS_CONTROLLER_BODY_TIMEOUT_S": str(TIMEOUT_S),
        "COSMOS_CONTROLLER_BODY_MIN_BYTES_PER_S": str(RATE),
    }
    with running_service("services.controller.app:app", directory / "logs", env) as service:
        yield service


def connect(service: ServiceProcess) -> socket.socket:
    host, port = service.url.removeprefix("http://").split(":")
    return socket.create_connection((host, int(port)), timeout=10)


def start_upload(
    service: ServiceProcess, size: int, sent: int, key: str | None = None
) -> socket.socket:
    """A ``POST /searches`` declaring ``size`` bytes, of which ``sent`` are sent now, with the
    API key ``key`` (None: the controller's :data:`KEY`; ``""``: no ``Authorization``)."""
    sock = connect(service)
    key = KEY["key"] if key is None else key
    authorization = f"Authorization: Bearer {key}\r\n" if key else ""
    head = (
        f"POST /searches?scene=demo HTTP/1.1\r\nHost: test\r\nContent-Type: image/png\r\n"
        f"{authorization}Content-Length: {size}\r\n\r\n"
    )
    sock.sendall(head.encode() + b"\0" * sent)
    return sock


def answer(sock: socket.socket, timeout_s: float) -> tuple[int, dict[str, str], bytes] | None:
    """The response's status, headers and body, or None if none came within ``timeout_s``."""
    sock.settimeout(timeout_s)
    data = b""
    try:
        while b"\r\n\r\n" not in data:
            chunk = sock.recv(65536)
            if not chunk:
                return None if not data else _parse(data)
            data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        length = int(dict(_headers(head)).get("content-length", "0"))
        while len(data) - len(head) - 4 < length:  # the body may come in later segments
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    except TimeoutError:
        return None
    return _parse(data)


HANDLED = {
    "urn:cosmos:problem:unsupported-image-format",  # its zeros are no image
    "urn:cosmos:problem:stage-unavailable",  # once the broker found no stage (none runs)
}


def handled(reply: tuple[int, dict[str, str], bytes] | None) -> bool:
    """Whether ``reply`` is the app's answer to an upload it read (not the body bounds')."""
    return reply is not None and json.loads(reply[2]).get("type") in HANDLED


def _headers(head: bytes) -> list[tuple[str, str]]:
    lines = head.decode("latin-1").split("\r\n")[1:]
    return [(k.strip().lower(), v.strip()) for k, _, v in (line.partition(":") for line in lines)]


def _parse(data: bytes) -> tuple[int, dict[str, str], bytes]:
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), dict(_headers(head)), body


def closed(sock: socket.socket, timeout_s: float = 2.0) -> bool:
    """Whether the server closed the connection (after what it sent)."""
    sock.settimeout(timeout_s)
    try:
        while True:
            if not sock.recv(65536):
                return True
    except (TimeoutError, ConnectionResetError):
        return False


def fill_budget(service: ServiceProcess, stack: ExitStack) -> list[socket.socket]:
    """Two maximal uploads, half sent: the budget is full until they finish or go away."""
    holders = [stack.enter_context(start_upload(service, LIMIT, LIMIT // 2)) for _ in range(2)]
    time.sleep(0.2)  # both admitted
    return holders


@pytest.mark.slow
def test_a_request_waits_for_bytes_and_is_admitted_once_they_are_free(controller):
    with ExitStack() as stack:
        first, second = fill_budget(controller, stack)
        waiting = stack.enter_context(start_upload(controller, LIMIT, LIMIT))
        assert answer(waiting, 0.4) is None  # not admitted: its body is not read
        first.sendall(b"\0" * (LIMIT - LIMIT // 2))
        assert handled(answer(first, 5.0))  # read, handed to the app
        assert handled(answer(waiting, WAIT_S))  # admitted when the first's bytes came free
        second.sendall(b"\0" * (LIMIT - LIMIT // 2))
        assert handled(answer(second, 5.0))


@pytest.mark.slow
def test_a_request_that_waits_too_long_gets_503_with_retry_after_and_is_not_reset(controller):
    with ExitStack() as stack:
        fill_budget(controller, stack)
        started = time.monotonic()
        # The whole body is sent before the answer is read, as most clients do.
        refused = stack.enter_context(start_upload(controller, LIMIT, LIMIT))
        status, headers, body = answer(refused, WAIT_S + 3.0)
        waited = time.monotonic() - started
        assert status == 503
        assert WAIT_S - 0.2 <= waited < WAIT_S + 2.0
        assert headers["content-type"] == "application/problem+json"
        assert int(headers["retry-after"]) >= 1
        problem = json.loads(body)
        assert problem["status"] == 503
        assert "try again" in problem["detail"]
        # Its body was read and dropped: the connection ends in a FIN. Closed with the body
        # unread, it would end in a reset, which may cost a client still sending its answer.
        assert closed(refused)


@pytest.mark.slow
def test_an_early_answer_waits_a_while_for_the_rest_of_the_body_then_closes(controller):
    with ExitStack() as stack:
        fill_budget(controller, stack)
        refused = stack.enter_context(start_upload(controller, LIMIT, 1000))
        assert answer(refused, WAIT_S + 3.0)[0] == 503
        answered = time.monotonic()
        assert closed(refused, LINGER_IDLE_S + 2.0)  # no more came: closed once idle
        assert time.monotonic() - answered >= LINGER_IDLE_S - 0.3


@pytest.mark.slow
def test_a_trickling_body_gets_408_and_its_bytes_are_released(controller):
    with ExitStack() as stack:
        slow = [stack.enter_context(start_upload(controller, LIMIT, 1000)) for _ in range(2)]
        started = time.monotonic()
        for sock in slow:
            status, headers, body = answer(sock, TIMEOUT_S + LIMIT / RATE + 3.0)
            assert status == 408
            assert headers["content-type"] == "application/problem+json"
            assert json.loads(body)["detail"].startswith("the request body did not arrive")
            assert closed(sock, LINGER_IDLE_S + 2.0)
        assert time.monotonic() - started >= TIMEOUT_S + LIMIT / RATE - 0.3
        # Their bytes are free again: a maximal upload is admitted and read at once.
        started = time.monotonic()
        fresh = stack.enter_context(start_upload(controller, LIMIT, LIMIT))
        assert handled(answer(fresh, 2.0))
        assert time.monotonic() - started < 1.0


@pytest.mark.slow
def test_small_requests_and_gets_do_not_wait_behind_large_uploads(controller):
    with ExitStack() as stack:
        fill_budget(controller, stack)
        waiting = stack.enter_context(start_upload(controller, LIMIT, LIMIT))
        for _ in range(3):
            started = time.monotonic()
            small = stack.enter_context(start_upload(controller, 30_000, 30_000))
            assert handled(answer(small, 1.0))  # read and handled while the large one waits
            probe = stack.enter_context(connect(controller))
            probe.sendall(b"GET /livez HTTP/1.1\r\nHost: test\r\n\r\n")
            assert answer(probe, 1.0)[0] == 200
            assert time.monotonic() - started < 0.5
        assert answer(waiting, 0.05) is None  # still waiting for large bytes


@pytest.mark.slow
@pytest.mark.parametrize("key", ["", "cosmos_not-a-key-of-this-controller"])
def test_an_upload_without_a_valid_key_is_refused_before_its_body_is_admitted_or_read(
    controller, key
):
    with ExitStack() as stack:
        first, _ = fill_budget(controller, stack)  # a keyed upload would now wait 1.5 s
        started = time.monotonic()
        stranger = stack.enter_context(start_upload(controller, LIMIT, 1000, key=key))
        status, headers, body = answer(stranger, 1.0)  # the rest of its body is never sent
        assert time.monotonic() - started < 0.5  # not in line for the budget
        assert status == 401
        assert headers["content-type"] == "application/problem+json"
        assert headers["www-authenticate"].startswith("Bearer")
        assert json.loads(body)["type"] == "urn:cosmos:problem:unauthorized"
        assert closed(stranger, LINGER_IDLE_S + 2.0)  # the rest never came
        # It held no bytes: once one holder's upload is done, a keyed one is admitted at once.
        first.sendall(b"\0" * (LIMIT - LIMIT // 2))
        assert handled(answer(first, 5.0))
        started = time.monotonic()
        fresh = stack.enter_context(start_upload(controller, LIMIT, LIMIT))
        assert handled(answer(fresh, 2.0))
        assert time.monotonic() - started < 1.0


def test_the_test_sizes_are_large_and_small_as_intended():
    limits = BodyLimits.for_limit(LIMIT, budget_bytes=2 * LIMIT)
    assert 30_000 <= limits.small_bytes < LIMIT // 2  # the small request above is small
