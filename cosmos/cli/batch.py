"""``cosmos search a.jpg b.jpg … --scene S``: many photos (a survey flight's), each searched once,
a line said per photo as its search ends, and the answers written as a table (``--poses``:
:mod:`cosmos.cli.pose_table`).

At most ``--concurrency`` searches are in the controller at a time: each of as many workers
submits a photo, follows its search to the end and takes the next photo, so a flight of
hundreds neither floods the controller's queue nor outruns a key's quota (a refusal that says
when to come back is waited out, as for one photo), and a slow search holds up only its own
worker. A photo that cannot be read, that the controller refuses, or that finds it out of
reach is said and kept in the table with why; so is a search whose end could not be followed
(the controller keeps it, under the id its row gives); the others go on. The answers come in
the order the photos were given.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import httpx

from cosmos.cli.pose_table import Row, not_searched, row_of
from services.common.contracts.search import Search
from services.controller.client import ControllerClient, ControllerError

__all__ = ["Submit", "search_all", "summary"]

Submit = Callable[[bytes], Search]
"""Submits one photo's bytes with the command's options; raises :class:`ControllerError` when
the controller refuses it, :class:`httpx.TransportError` when it cannot be reached."""


def summary(image: str, row: Row) -> str:
    """The line said for one photo once its search has ended."""
    if "renders" not in row:  # no result: not searched, failed, or not followed to its end
        return f"{image}: {row['status']}: {row.get('reason', '')}"
    answer = row["answer"]
    said = answer if row.get("confirmed") else f"{answer}, not confirmed"
    if "x" in row:
        where = (
            f"position ({row['x']:.2f}, {row['y']:.2f}, {row['z']:.2f}), yaw/pitch/roll "
            f"({row['yaw_deg']:.1f}, {row['pitch_deg']:.1f}, {row['roll_deg']:.1f})°, "
            f"fov {row['fov_deg']:.1f}° ({row['intrinsics']})"
        )
    else:
        where = f"θ {row['theta_deg']:.1f}° φ {row['phi_deg']:.1f}°"
    return f"{image}: {said}: {where}, {row['renders']} render(s)"


def _ended(client: ControllerClient, search: Search) -> Search:
    """``search`` once it has ended (its events followed to the last)."""
    final = search
    for item in client.follow(search.id):
        if isinstance(item, Search):
            final = item
    return final


def _row(client: ControllerClient, path: Path, submit: Submit) -> Row:
    """One photo submitted and its search followed to the end: its row."""
    try:
        search = submit(path.read_bytes())
    except OSError as exc:
        return not_searched(str(path), f"cannot be read ({exc.strerror or exc})")
    except ControllerError as exc:
        return not_searched(str(path), f"refused ({exc.status}: {exc.detail})")
    except httpx.TransportError as exc:
        return not_searched(str(path), f"the controller could not be reached ({exc})")
    try:
        return row_of(str(path), _ended(client, search))
    except (ControllerError, httpx.TransportError) as exc:
        lost = f"not followed to its end ({exc}); the controller keeps it: ask for {search.id}"
        return {**row_of(str(path), search), "answer": "", "reason": lost}


def search_all(
    client: ControllerClient,
    images: Sequence[Path],
    submit: Submit,
    concurrency: int,
    say: Callable[[str], None] = print,
) -> list[Row]:
    """Each of ``images`` searched by ``concurrency`` workers (module docstring): their rows, in
    the order given. The workers are daemon threads: an interrupted command does not wait for
    the searches it follows (the controller keeps them)."""
    rows: list[Row | None] = [None] * len(images)
    todo: queue.SimpleQueue[int] = queue.SimpleQueue()
    for index in range(len(images)):
        todo.put(index)
    said = threading.Lock()
    failures: list[BaseException] = []

    def work() -> None:
        try:
            while True:
                try:
                    index = todo.get_nowait()
                except queue.Empty:
                    return
                row = _row(client, images[index], submit)
                with said:
                    rows[index] = row
                    say(summary(str(images[index]), row))
        except BaseException as exc:  # noqa: BLE001 - raised again by the command's thread
            failures.append(exc)

    workers = [threading.Thread(target=work, daemon=True) for _ in range(concurrency)]
    for worker in workers[: len(images)]:
        worker.start()
    for worker in workers[: len(images)]:
        while worker.is_alive():
            worker.join(0.2)  # in short waits, so that Ctrl-C reaches this thread
    if failures:
        raise failures[0]
    return [row for row in rows if row is not None]
