"""A bounded load of searches through a controller's HTTP API, followed through faults (a
controller that does not answer is asked again), and what became of them, counted.

What counts, per search the controller took (202):

* **answered**: it ended ``succeeded`` with a result;
* **lost**: it did not (failed, cancelled, vanished, or still unfinished at the deadline);
* **recorded twice**: its iterations' indices are not exactly 0, 1, ..., n - 1 (an iteration
  recorded twice repeats an index; one lost leaves a gap);
* **resumed**: it was running when the controller was killed, and its final iterations begin
  with the ones recorded before the kill (:meth:`Searches.snapshot`), so it went on from its
  last recorded iteration, not from the start;
* **found**: it answered the grid pose its target was rendered from.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import httpx

from services.common.contracts.search import TERMINAL_STATUSES, Search
from services.common.geometry.pose import GridIndex

__all__ = ["Counts", "Searches"]


@dataclass(frozen=True)
class Counts:
    submitted: int
    answered: int
    lost: int
    recorded_twice: int
    running_at_kill: int
    resumed: int
    found: int

    def line(self) -> str:
        return (
            f"submitted {self.submitted}, answered {self.answered}, lost {self.lost}, "
            f"recorded twice {self.recorded_twice}, running at the kill {self.running_at_kill}, "
            f"resumed {self.resumed}, found the target's pose {self.found}"
        )


class Searches:
    """Searches submitted to the controllers at ``urls`` with ``headers`` (the API key): each
    request goes to the first controller that answers it, so with controllers sharing a
    database, a search is followed through whichever is up."""

    def __init__(self, urls: Sequence[str], headers: Mapping[str, str]) -> None:
        self._controllers = [
            httpx.Client(base_url=url, headers=dict(headers), timeout=10.0) for url in urls
        ]
        self.truth: dict[str, GridIndex] = {}
        self.seen: dict[str, Search] = {}
        self.at_kill: dict[str, Search] = {}
        self.vanished: set[str] = set()

    def close(self) -> None:
        for client in self._controllers:
            client.close()

    def _ask(self, method: str, path: str, **request: Any) -> httpx.Response:
        """``method path`` of the first controller that answers; the last one's error if none
        does."""
        for client in self._controllers[:-1]:
            try:
                return client.request(method, path, **request)
            except httpx.TransportError:
                continue
        return self._controllers[-1].request(method, path, **request)

    def submit(
        self,
        image: bytes,
        truth: GridIndex,
        params: Mapping[str, Any],
        controller: int | None = None,
    ) -> str:
        """Submit a search to the first controller that answers, or to the ``controller``-th."""
        request: dict[str, Any] = {
            "content": image,
            "headers": {"Content-Type": "image/png"},
            "params": {key: str(value) for key, value in params.items()},
        }
        if controller is None:
            answer = self._ask("POST", "/searches", **request)
        else:
            answer = self._controllers[controller].post("/searches", **request)
        assert answer.status_code == 202, answer.text
        search_id: str = answer.json()["id"]
        self.truth[search_id] = truth
        return search_id

    def answered_by_each(self) -> list[int]:
        """How many searches each controller answers as last seen (any answers any)."""
        counts = []
        for client in self._controllers:
            same = 0
            for search_id, seen in self.seen.items():
                answer = client.get(f"/searches/{search_id}")
                if answer.status_code == 200:
                    same += Search.model_validate_json(answer.content) == seen
            counts.append(same)
        return counts

    def health(self, controller: int | None = None) -> dict[str, Any]:
        """The ``/health`` of the first controller that answers, or of the ``controller``-th
        (its replicas by name, with their loads and counts)."""
        if controller is None:
            answer = self._ask("GET", "/health")
        else:
            answer = self._controllers[controller].get("/health")
        answer.raise_for_status()
        found: dict[str, Any] = answer.json()
        return found

    def replicas(self, stage: str) -> list[dict[str, Any]]:
        """What the controller knows of each replica of ``stage``."""
        return [r for r in self.health()["replicas"] if r["stage"] == stage]

    def replica(self, name: str, controller: int | None = None) -> dict[str, Any]:
        (found,) = [r for r in self.health(controller)["replicas"] if r["name"] == name]
        return found

    def refresh(self) -> dict[str, Search]:
        """Ask for every search not seen ended yet; those the controller does not answer now
        keep what was seen last."""
        for search_id in self.truth:
            if search_id in self.seen and self._ended(search_id):
                continue
            try:
                answer = self._ask("GET", f"/searches/{search_id}")
            except httpx.TransportError:
                continue  # the controller is down or unreachable: ask again later
            if answer.status_code == 404:
                self.vanished.add(search_id)
            elif answer.status_code == 200:
                self.seen[search_id] = Search.model_validate_json(answer.content)
        return self.seen

    @property
    def recorded(self) -> int:
        """Iterations recorded over all searches, as last seen."""
        return sum(len(s.iterations) for s in self.seen.values())

    @property
    def running(self) -> list[Search]:
        return [s for s in self.seen.values() if s.status == "running"]

    @property
    def unfinished(self) -> list[str]:
        return [i for i in self.truth if i not in self.seen or not self._ended(i)]

    def _ended(self, search_id: str) -> bool:
        return search_id in self.vanished or self.seen[search_id].status in TERMINAL_STATUSES

    def wait(self, until: Any, timeout_s: float, what: str, poll_s: float = 0.3) -> None:
        """Refresh every ``poll_s`` until ``until()`` is true; fail naming ``what`` after
        ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.refresh()
            if until():
                return
            assert time.monotonic() < deadline, f"timed out waiting for {what}: {self.states()}"
            time.sleep(poll_s)

    def snapshot(self) -> int:
        """What each running search had recorded at the last refresh, kept as the searches
        running at the kill; how many. Taken from the refresh a wait ended on, not a new one:
        a one-render search can end in the time another refresh takes, and the kill would
        then find none running."""
        self.at_kill = {s.id: s for s in self.running if s.iterations}
        return len(self.at_kill)

    def states(self) -> dict[str, tuple[str, int]]:
        return {i: (s.status, len(s.iterations)) for i, s in self.seen.items()}

    def counts(self) -> Counts:
        final = [self.seen[i] for i in self.truth if i in self.seen and i not in self.vanished]
        answered = [s for s in final if s.status == "succeeded" and s.result is not None]
        return Counts(
            submitted=len(self.truth),
            answered=len(answered),
            lost=len(self.truth) - len(answered),
            recorded_twice=sum(not _contiguous(s) for s in final),
            running_at_kill=len(self.at_kill),
            resumed=sum(
                _begins_with(self.seen[i], before.iterations) for i, before in self.at_kill.items()
            ),
            found=sum(
                s.result is not None and s.result.pose.index == self.truth[s.id] for s in answered
            ),
        )


def _contiguous(search: Search) -> bool:
    return [it.index for it in search.iterations] == list(range(len(search.iterations)))


def _begins_with(search: Search, before: Sequence[Any]) -> bool:
    return len(search.iterations) >= len(before) and search.iterations[: len(before)] == tuple(
        before
    )
