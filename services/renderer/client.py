"""A small synchronous client of the renderer service (the CLI uses it)."""

from __future__ import annotations

from types import TracebackType

import httpx

from services.common.models import RenderAnnotations, RenderRequest, SceneSummary
from services.common.scene import SceneDetail

__all__ = ["RendererClient", "RendererError"]


class RendererError(RuntimeError):
    """The renderer answered with an error (its problem detail is the message)."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"renderer answered {status}: {detail}")
        self.status = status


class RendererClient:
    """Calls one renderer at ``base_url`` with explicit timeouts."""

    def __init__(self, base_url: str, timeout_s: float = 120.0) -> None:
        self._http = httpx.Client(base_url=base_url, timeout=httpx.Timeout(timeout_s, connect=5.0))

    def __enter__(self) -> RendererClient:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _check(self, response: httpx.Response) -> httpx.Response:
        if response.status_code >= 400:
            try:
                detail = str(response.json().get("detail", response.text))
            except ValueError:
                detail = response.text
            raise RendererError(response.status_code, detail)
        return response

    def scenes(self) -> list[SceneSummary]:
        """``GET /scenes``."""
        data = self._check(self._http.get("/scenes")).json()
        return [SceneSummary.model_validate(item) for item in data]

    def scene(self, scene_id: str) -> SceneDetail:
        """``GET /scenes/{id}``."""
        return SceneDetail.model_validate(self._check(self._http.get(f"/scenes/{scene_id}")).json())

    def render_png(self, request: RenderRequest) -> bytes:
        """``POST /render``: PNG bytes."""
        body = request.model_dump(mode="json", exclude_none=True)
        return self._check(self._http.post("/render", json=body)).content

    def annotations(self, request: RenderRequest) -> RenderAnnotations:
        """``POST /render/annotations``."""
        body = request.model_dump(mode="json", exclude_none=True)
        response = self._check(self._http.post("/render/annotations", json=body))
        return RenderAnnotations.model_validate(response.json())
