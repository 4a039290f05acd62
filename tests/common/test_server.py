"""The HTTP server of every service (:mod:`services.common.server`) against real processes: a
request head over the limit gets 431 at once, and connections that never complete a head are
closed after the deadline while normal requests are served as usual."""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from cosmos.launch import ServiceProcess, stop_service, wait_healthy
from services.common.server import DEFAULT_MAX_HEAD_BYTES, RedactSecrets
from tests.support import ROOT, free_port, running_service

pytestmark = pytest.mark.slow

APP = "services.optimizer.app:app"  # the quickest service to start
HEAD_TIMEOUT_S = 2.0
HALF_OPEN = 300


@pytest.fixture(scope="module")
def launched(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A service started the way ``cosmos up`` and the tests start every service."""
    with running_service(APP, tmp_path_factory.mktemp("server")) as service:
        yield service


@pytest.fixture(scope="module")
def quick_deadline(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A service run by the server module with a short head deadline, so the test is short."""
    port = free_port()
    log = Path(tmp_path_factory.mktemp("server-deadline")) / "optimizer.log"
    command = [sys.executable, "-m", "services.common.server", APP, "--port", str(port)]
    command += ["--head-timeout-s", str(HEAD_TIMEOUT_S)]
    with log.open("wb") as sink:
        process = subprocess.Popen(command, cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT)
    service = ServiceProcess(url=f"http://127.0.0.1:{port}", process=process, log=log)
    wait_healthy(service)
    try:
        yield service
    finally:
        stop_service(service)


def address(service: ServiceProcess) -> tuple[str, int]:
    host, port = service.url.removeprefix("http://").split(":")
    return host, int(port)


def read_all(sock: socket.socket, timeout_s: float) -> tuple[bytes, bool]:
    """What the server sends within ``timeout_s``, and whether it closed the connection."""
    sock.settimeout(timeout_s)
    received = b""
    try:
        while chunk := sock.recv(65536):
            received += chunk
    except TimeoutError:
        return received, False
    except ConnectionResetError:
        pass
    return received, True


def test_a_huge_header_gets_431_at_once(launched):
    """A header of 64 MB was answered 200 after 7 s; now the server stops reading past the
    limit and answers 431 with a problem."""
    started = time.perf_counter()
    with socket.create_connection(address(launched)) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Big: ")
        sent = 0
        try:
            while sent < 64 * 2**20:
                sock.sendall(b"a" * 65536)
                sent += 65536
        except OSError:  # the server closed the connection
            pass
        answer, closed = read_all(sock, 10.0)
    elapsed = time.perf_counter() - started
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
    assert closed
    assert b"application/problem+json" in answer
    assert b"request-head-too-large" in answer
    assert sent < 8 * 2**20, sent
    assert elapsed < 3.0, elapsed


@pytest.mark.parametrize(
    ("header_bytes", "status"),
    [(DEFAULT_MAX_HEAD_BYTES - 1024, 200), (DEFAULT_MAX_HEAD_BYTES + 1024, 431)],
)
def test_a_whole_head_is_measured_too(launched, header_bytes, status):
    """A head that arrives complete in one write is measured by its parsed parts."""
    head = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * header_bytes + b"\r\n\r\n"
    with socket.create_connection(address(launched)) as sock:
        sock.sendall(head)
        answer, _ = read_all(sock, 1.0)
    assert answer.startswith(f"HTTP/1.1 {status} ".encode()), answer[:200]


def test_half_sent_heads_are_closed_after_the_deadline(quick_deadline):
    """Hundreds of connections that send part of a head, or nothing: normal requests are still
    answered promptly, and every such connection is closed once the deadline passes."""
    target = address(quick_deadline)
    half_open = []
    try:
        for i in range(HALF_OPEN):
            sock = socket.create_connection(target)
            if i % 10:  # every tenth sends nothing at all
                sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Slow: ")
            half_open.append(sock)
        opened = time.monotonic()
        with httpx.Client(base_url=quick_deadline.url, timeout=5.0) as client:
            for _ in range(5):
                started = time.perf_counter()
                assert client.get("/health").status_code == 200
                assert time.perf_counter() - started < 0.5
        for sock in half_open:  # nothing closed before the deadline
            sock.setblocking(False)
            with pytest.raises(BlockingIOError):
                sock.recv(1)
        time.sleep(max(0.0, opened + HEAD_TIMEOUT_S + 1.0 - time.monotonic()))
        answers = [read_all(sock, 1.0) for sock in half_open]
    finally:
        for sock in half_open:
            sock.close()
    assert all(closed for _, closed in answers)
    for i, (answer, _) in enumerate(answers):
        # A connection that sent part of a head is told why; one that sent nothing is not.
        assert answer.startswith(b"HTTP/1.1 408 ") if i % 10 else answer == b"", (i, answer)


def test_the_deadline_ends_with_the_head(quick_deadline, service_token):
    """A body that arrives after the head deadline is still read: only the head is timed."""
    with socket.create_connection(address(quick_deadline)) as sock:
        sock.sendall(
            b"POST /next-pose HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            + f"Authorization: Bearer {service_token}\r\n".encode()
            + b"Content-Length: 2\r\n\r\n"
        )
        time.sleep(HEAD_TIMEOUT_S + 0.5)
        sock.sendall(b"{}")
        answer, _ = read_all(sock, 1.0)
    assert answer.startswith(b"HTTP/1.1 422 "), answer[:200]


def test_the_container_runs_every_service_in_this_server():
    dockerfile = (ROOT / "Dockerfile").read_text()
    [command] = [line for line in dockerfile.splitlines() if line.startswith("CMD ")]
    assert "python -m services.common.server services.${SERVICE}.app:app" in command
    assert f"--max-head-bytes {DEFAULT_MAX_HEAD_BYTES}" in command
    assert "uvicorn" not in command


def test_a_stopping_server_ends_its_event_streams_and_exits_cleanly(tmp_path):
    """SIGTERM with a health stream open (a browser left on the page): the stream ends as a
    complete response and the process exits by itself. Without the server's stop flag, uvicorn
    waits for the endless response until its graceful timeout cancels it mid-stream (the client
    reads a broken response), or the launcher kills the process."""
    env = {
        "COSMOS_CONTROLLER_DATABASE_URL": f"sqlite:///{tmp_path}/controller.sqlite3",
        "COSMOS_CONTROLLER_AUTH": "off",
        **{
            f"COSMOS_CONTROLLER_{stage}_URLS": f"http://127.0.0.1:{free_port()}"
            for stage in ("RENDERER", "DETECTOR", "OPTIMIZER")
        },
    }
    with running_service("services.controller.app:app", tmp_path / "logs", env) as service:
        following = threading.Event()
        outcome: list[str] = []

        def follow() -> None:
            try:
                with (
                    httpx.Client(timeout=30.0) as client,
                    client.stream("GET", f"{service.url}/health/events") as events,
                ):
                    for line in events.iter_lines():
                        if line.startswith("event: health"):
                            following.set()
                outcome.append("ended")
            except httpx.HTTPError as exc:
                outcome.append(f"broken: {exc!r}")

        thread = threading.Thread(target=follow, daemon=True)
        thread.start()
        assert following.wait(30), "no health event came"
        stop_service(service, timeout_s=30.0)
        thread.join(30)
        assert outcome == ["ended"]
        # by itself: uvicorn raises the signal it caught again once it shut down, not killed
        assert service.process.returncode in {0, -signal.SIGTERM}


SECRET = "s3cret-value"
KEY = "cosmos_" + "k" * 43


def test_a_key_in_the_query_string_never_reaches_the_access_log(launched):
    """A key sent as ``?api_key=…`` is refused by the controller, but uvicorn's access log wrote
    the whole query: the server's log has every sensitive value redacted, and the rest as sent."""
    query = f"api_key={SECRET}&lat=3&token={SECRET}&X-Api-Key={KEY}&access_token={SECRET}"
    answer = httpx.get(f"{launched.url}/health?{query}", headers={"Authorization": f"Bearer {KEY}"})
    assert answer.status_code == 200
    deadline = time.monotonic() + 5
    while "/health?api_key=" not in launched.log.read_text() and time.monotonic() < deadline:
        time.sleep(0.05)
    log = launched.log.read_text()
    line = next(line for line in log.splitlines() if "/health?api_key=" in line)
    assert "?api_key=REDACTED&lat=3&token=REDACTED&X-Api-Key=REDACTED&access_token=REDACTED" in line
    assert SECRET not in log
    assert KEY not in log


def test_other_log_lines_lose_their_secrets_too():
    """A service's own line that quotes a request or a header keeps its words, not its secrets."""
    record = logging.LogRecord(
        "cosmos.controller", logging.WARNING, __file__, 1, "refused %s with %s", None, None
    )
    record.args = (f"/searches?scene=demo&api_key={SECRET}", f"Authorization: Bearer {KEY}")
    assert RedactSecrets().filter(record)
    assert record.getMessage() == (
        "refused /searches?scene=demo&api_key=REDACTED with Authorization: Bearer REDACTED"
    )
    try:
        raise ValueError(f"GET /searches?token={SECRET}")
    except ValueError:
        failed = logging.LogRecord(
            "cosmos.controller", logging.ERROR, __file__, 1, "crashed", None, sys.exc_info()
        )
    assert RedactSecrets().filter(failed)
    assert SECRET not in logging.Formatter().format(failed)
