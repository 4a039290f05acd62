"""A small synchronous client of the controller: submit a search, follow it, fetch its plots."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import httpx

from services.common.client import ServiceCallError, ServiceClient
from services.common.contracts.search import Iteration, Search
from services.common.images import media_type_of

__all__ = ["ControllerClient", "ControllerError"]


class ControllerError(ServiceCallError):
    """The controller answered with an error."""


class ControllerClient(ServiceClient):
    """Calls the controller at ``base_url`` with explicit timeouts, sending ``api_key`` as
    ``Authorization: Bearer`` (:func:`services.controller.keys.client_key` finds the local one)."""

    service = "controller"
    error = ControllerError

    def __init__(
        self, base_url: str, timeout_s: float = 60.0, *, api_key: str | None = None
    ) -> None:
        super().__init__(base_url, timeout_s)
        if api_key is not None:
            self._http.headers["Authorization"] = f"Bearer {api_key}"

    def submit(self, image: bytes, scene: str, **options: Any) -> Search:
        """``POST /searches`` with the image as the body; ``options`` are the optional
        :class:`~services.common.contracts.search.SearchOptions` (None values left out)."""
        query = {k: str(v) for k, v in options.items() if v is not None}
        response = self._http.post(
            "/searches",
            content=image,
            params={"scene": scene, **query},
            headers={"Content-Type": media_type_of(image)},
        )
        return Search.model_validate(self._check(response).json())

    def get(self, search_id: str) -> Search:
        return Search.model_validate(self._check(self._http.get(f"/searches/{search_id}")).json())

    def follow(self, search_id: str, timeout_s: float = 600.0) -> Iterator[Iteration | Search]:
        """Iterations as they are recorded, then the finished search (server-sent events)."""
        with self._http.stream(
            "GET", f"/searches/{search_id}/events", timeout=httpx.Timeout(timeout_s, connect=5.0)
        ) as response:
            self._check(response)
            event = ""
            for line in response.iter_lines():
                if line.startswith("event: "):
                    event = line[len("event: ") :]
                elif line.startswith("data: "):
                    data = json.loads(line[len("data: ") :])
                    if event == "iteration":
                        yield Iteration.model_validate(data)
                    elif event == "end":
                        yield self.get(search_id)
                        return

    def plot(self, search_id: str, name: str) -> bytes:
        """``trajectory.png`` or ``distance.png``."""
        return self._check(self._http.get(f"/searches/{search_id}/{name}")).content
