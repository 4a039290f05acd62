"""Controller settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator

from services.common.settings import ServiceSettings
from services.controller.broker import Heuristic

__all__ = ["ControllerSettings"]


def _urls(value: str) -> list[str]:
    return [part.strip().rstrip("/") for part in value.split(",") if part.strip()]


class ControllerSettings(ServiceSettings):
    """Replica URLs per stage (comma-separated), the database, and limits.

    ``COSMOS_RENDERER_URLS``, ``COSMOS_DETECTOR_URLS``, ``COSMOS_OPTIMIZER_URLS``;
    ``COSMOS_DATABASE_URL`` (``sqlite:///path``).

    ``COSMOS_RENDER_SPP``, which the renderer reads too, is read as
    ``COSMOS_CONTROLLER_VIEW_SPP`` for one more release, with a warning.
    """

    renamed = {"COSMOS_RENDER_SPP": "controller_view_spp"}

    renderer_urls: str = "http://127.0.0.1:8001"
    detector_urls: str = "http://127.0.0.1:8002"
    optimizer_urls: str = "http://127.0.0.1:8003"
    database_url: str = "sqlite:///data/controller.sqlite3"
    broker_heuristic: Heuristic = Heuristic.SHORTEST_EXPECTED
    discover_replicas: bool = False
    discovery_interval_s: Annotated[float, Field(gt=0, le=3600)] = 10.0
    max_concurrent_searches: Annotated[int, Field(ge=1, le=1000)] = 4
    default_max_iterations: Annotated[int, Field(ge=1, le=500)] = 40
    controller_view_spp: Annotated[int, Field(ge=1, le=1024)] | None = 8
    """Samples per pixel of the search views (None: the renderer's default). 8 is the cheapest
    setting at which detection and search success did not drop (docs/RESULTS.md, ``--sweep``)."""
    render_width: Annotated[int, Field(ge=8, le=8192)] | None = None
    """Film width of the search views (the renderer keeps the scene's aspect); None: the
    scene's own. ``cosmos bench --sweep`` measures what detection and searches lose."""
    render_timeout_s: Annotated[float, Field(gt=0, le=600)] = 60.0
    detect_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    optimize_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    connect_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    max_upload_bytes: Annotated[int, Field(ge=1024)] = 20 * 1024 * 1024
    max_image_pixels: Annotated[int, Field(ge=64)] = 4096 * 4096
    max_image_side: Annotated[int, Field(ge=8)] = 8192

    @field_validator("renderer_urls", "detector_urls", "optimizer_urls")
    @classmethod
    def _some_url(cls, value: str) -> str:
        urls = _urls(value)
        if not urls:
            raise ValueError("give at least one replica URL")
        for url in urls:
            if not url.startswith(("http://", "https://")):
                raise ValueError(f"{url!r} is not an http(s) URL")
        return value

    def pools(self) -> dict[str, list[str]]:
        """Replica URLs per stage."""
        return {
            "renderer": _urls(self.renderer_urls),
            "detector": _urls(self.detector_urls),
            "optimizer": _urls(self.optimizer_urls),
        }

    def timeouts(self) -> dict[str, float]:
        return {
            "renderer": self.render_timeout_s,
            "detector": self.detect_timeout_s,
            "optimizer": self.optimize_timeout_s,
        }
