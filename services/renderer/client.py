"""A small synchronous client of the renderer service (the CLI uses it)."""

from __future__ import annotations

from services.common.client import ServiceCallError, ServiceClient
from services.common.contracts.render import (
    RenderAnnotations,
    RenderRequest,
    SceneDetail,
    SceneSummary,
)
from services.common.geometry.free_camera import FreeCamera
from services.renderer.depth import DepthImage

__all__ = ["RendererClient", "RendererError"]


class RendererError(ServiceCallError):
    """The renderer answered with an error."""


class RendererClient(ServiceClient):
    """Calls one renderer at ``base_url`` with explicit timeouts."""

    service = "renderer"
    error = RendererError

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

    def depth(self, request: RenderRequest) -> DepthImage:
        """``POST /render/depth``: the view's depth and object ids."""
        body = request.model_dump(mode="json", exclude_none=True)
        return DepthImage.from_npz(self._check(self._http.post("/render/depth", json=body)).content)

    def render_camera(
        self,
        scene: str,
        camera: FreeCamera,
        *,
        width: int | None = None,
        height: int | None = None,
        spp: int | None = None,
        seed: int = 0,
    ) -> tuple[bytes, RenderAnnotations]:
        """A free camera's view: ``POST /render`` (PNG bytes) and ``POST /render/annotations``
        (its ground truth) for the same request; ``camera``'s pixel intrinsics are in pixels of
        the film (the scene camera's unless ``width``/``height`` are given)."""
        request = RenderRequest(
            scene=scene, camera=camera, width=width, height=height, spp=spp, seed=seed
        )
        return self.render_png(request), self.annotations(request)
