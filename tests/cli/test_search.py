"""``cosmos search``'s free-camera flags: the photo's lens goes with ``--free`` only (the
search end to end: tests/test_e2e_free.py)."""

from __future__ import annotations

import socket
from pathlib import Path

import httpx
import pytest

from cosmos.cli import main, unreachable


@pytest.mark.parametrize(
    "flags",
    [
        ["--fov", "50"],
        ["--intrinsics", "300,300,160,120"],
        ["--distortion", "0,0,0,0"],
        ["--no-exif"],
        ["--attitude", "80,0"],
    ],
)
def test_lens_flags_need_free(tmp_path: Path, capsys: pytest.CaptureFixture[str], flags) -> None:
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"")
    argv = ["search", str(photo), "--scene", "demo", "--url", "http://127.0.0.1:9", *flags]
    assert main(argv) == 2
    assert f"{flags[0]} go with --free" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "field", "value"),
    [
        (
            ["search", "p.jpg", "--scene", "demo", "--free", "--distortion", "-0.12,0.03,0,0"],
            "distortion",
            "-0.12,0.03,0,0",
        ),
        (
            ["search", "p.jpg", "--scene", "demo", "--free", "--distortion", "-.1,0,0,0"],
            "distortion",
            "-.1,0,0,0",
        ),
        (["render", "--position", "-4,3,5", "--look-at", "0,-1,0"], "position", "-4,3,5"),
        (
            ["search", "p.jpg", "--scene", "demo", "--free", "--attitude", "60,-2.5"],
            "attitude",
            "60,-2.5",
        ),
    ],
    ids=["search-barrel-lens", "search-no-leading-zero", "render-position", "search-attitude"],
)
def test_a_list_may_start_with_a_minus_sign(argv: list[str], field: str, value: str) -> None:
    """A barrel lens's k1 is negative: argparse took ``-0.12,…`` for an unknown flag."""
    from cosmos.cli import _parser

    assert getattr(_parser().parse_args(argv), field) == value


@pytest.mark.parametrize(
    ("agrees", "done", "said"),
    [(True, False, "agrees"), (False, False, "disagrees"), (None, True, "agrees")],
    ids=["rivals-next", "disagrees", "older-record"],
)
def test_a_free_iteration_says_whether_its_render_agreed(
    capsys: pytest.CaptureFixture[str], agrees: bool | None, done: bool, said: str
) -> None:
    """A render that agrees while its rivals are rendered next is not ``done``."""
    from cosmos.cli.follow import _print_free_iteration
    from services.common.contracts.optimize import GridPose
    from services.common.contracts.search import Iteration, StageTimings
    from services.common.geometry.pose import GridIndex

    pose = GridPose(index=GridIndex(lat=1, lon=0), theta_deg=15.0, phi_deg=0.0)
    it = Iteration(
        index=0,
        pose=pose,
        image_size=(320, 240),
        detections=(),
        timings=StageTimings(),
        done=done,
        agrees=agrees,
    )
    _print_free_iteration(it)
    assert capsys.readouterr().out.rstrip().endswith(f"  {said}")


def _closed_port() -> int:
    """A local port that nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize("command", ["search", "scenes", "render"])
def test_no_stack_at_the_url_is_one_line_that_says_what_to_do(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """A search before ``cosmos up`` printed httpx's traceback."""
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"\x89PNG\r\n\x1a\n")
    url = f"http://127.0.0.1:{_closed_port()}"
    argv = {
        "search": ["search", str(photo), "--scene", "demo", "--url", url, "--retry-for", "0"],
        "scenes": ["scenes", "--url", url],
        "render": ["render", "--scene", "demo", "--url", url, "-o", str(tmp_path / "v.png")],
    }[command]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"cosmos: {url} cannot be reached (")
    assert "cosmos up" in err
    assert "Traceback" not in err
    assert err.count("\n") == 1


def test_a_service_that_does_not_answer_in_time_is_named() -> None:
    request = httpx.Request("POST", "http://10.0.0.7:8000/searches")
    said = unreachable(httpx.ReadTimeout("timed out", request=request))
    assert said.startswith("http://10.0.0.7:8000 did not answer in time: ")


def test_a_flight_keeps_at_most_concurrency_searches_in_the_controller(tmp_path: Path) -> None:
    """At most ``concurrency`` searches are in the controller at a time, and a slow one holds up
    only its own worker: the first search ends only once the last photo went in (waiting for
    the oldest search before the next photo, it would have waited out its 10 s). The rows come
    back in the order the photos were given; a search whose end could not be followed keeps its
    row, with its id to ask for."""
    import threading
    from datetime import UTC, datetime

    from cosmos.cli.batch import search_all
    from services.common.contracts.optimize import GridPose
    from services.common.contracts.search import Search
    from services.common.geometry.pose import GridIndex

    start = GridPose(index=GridIndex(lat=0, lon=0), theta_deg=0.0, phi_deg=0.0)
    now = datetime.now(UTC)

    def search(n: int, status: str) -> Search:
        times = {"created_at": now, "updated_at": now, "target_size": (320, 240)}
        return Search(
            id=f"s{n}", status=status, scene="demo", strategy="reprojection", start=start,
            seed=0, max_iterations=5, **times,
        )  # fmt: skip

    running: set[str] = set()
    most = 0
    lock = threading.Lock()
    last_in = threading.Event()  # the last photo was submitted
    first_waited: list[bool] = []

    class Controller:
        def follow(self, search_id: str):
            if search_id == "s0":  # a slow search: it ends once the last photo is in
                first_waited.append(last_in.wait(timeout=10))
            with lock:
                running.discard(search_id)
            if search_id == "s3":  # the controller's stream broke off: the search goes on there
                raise httpx.ReadTimeout("timed out")
            yield search(int(search_id[1:]), "failed")

    def submit(image: bytes) -> Search:
        nonlocal most
        if image == b"6":
            last_in.set()
        if image == b"5":  # the controller went away for a moment
            raise httpx.ConnectError("connection refused")
        made = search(int(image), "queued")
        with lock:
            running.add(made.id)
            most = max(most, len(running))
        return made

    photos = []
    for n in range(7):
        photos.append(tmp_path / f"{n}.png")
        photos[-1].write_bytes(str(n).encode())
    said: list[str] = []
    rows = search_all(Controller(), photos, submit, 3, said.append)  # type: ignore[arg-type]
    assert first_waited == [True]
    assert most <= 3
    assert not running
    assert [row.get("search_id") for row in rows] == ["s0", "s1", "s2", "s3", "s4", None, "s6"]
    assert rows[5]["status"] == "not searched"
    assert "the controller could not be reached" in str(rows[5]["reason"])
    assert len(said) == 7
    assert rows[3]["status"] == "queued"
    assert "not followed to its end" in str(rows[3]["reason"])
    assert "ask for s3" in str(rows[3]["reason"])
    assert f"{photos[3]}: queued: not followed to its end" in "\n".join(said)
