"""Controller settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator, model_validator

from services.common import DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_UPLOAD_BYTES
from services.common.auth import ServiceTokenSettings
from services.common.bodies import (
    DEFAULT_BODY_TIMEOUT_S,
    DEFAULT_BODY_WAIT_S,
    DEFAULT_MIN_BYTES_PER_S,
    BodyLimits,
)
from services.common.contracts.search import ViewSpp, ViewWidth
from services.controller.broker import Heuristic

__all__ = ["ControllerSettings"]


def _urls(value: str) -> list[str]:
    return [part.strip().rstrip("/") for part in value.split(",") if part.strip()]


class ControllerSettings(ServiceTokenSettings):
    """Replica URLs per stage (comma-separated), the database, limits, API keys and quotas.

    ``COSMOS_CONTROLLER_RENDERER_URLS``, ``COSMOS_CONTROLLER_DETECTOR_URLS``,
    ``COSMOS_CONTROLLER_OPTIMIZER_URLS``; ``COSMOS_CONTROLLER_DATABASE_URL`` (``sqlite:///path`` or
    ``postgresql://…``).
    ``COSMOS_CONTROLLER_AUTH`` (default on: every route but ``/health`` and the docs wants an
    API key; ``off`` for development only), ``COSMOS_CONTROLLER_CORS_ORIGINS`` (none by default),
    ``COSMOS_CONTROLLER_QUOTA_…`` per key, ``COSMOS_CONTROLLER_RETENTION_S``."""

    controller_renderer_urls: str = "http://127.0.0.1:8001"
    """The renderer's replicas, comma-separated."""
    controller_detector_urls: str = "http://127.0.0.1:8002"
    """The detector's replicas, comma-separated."""
    controller_optimizer_urls: str = "http://127.0.0.1:8003"
    """The optimizer's replicas, comma-separated."""
    controller_database_url: str = "sqlite:///data/controller.sqlite3"
    """The searches' and keys' database: ``sqlite:///path`` (one controller), or
    ``postgresql://user:password@host:port/database``, which several controllers share."""
    controller_lease_s: Annotated[float, Field(gt=0, le=3600)] = 10.0
    """PostgreSQL only: seconds a controller's lease on a search it runs lasts without a
    heartbeat (renewed every third of it); a controller that dies or is cut off from the
    database loses its searches to another after this long. A connection to the database that
    gets no answer is given up after half of it."""
    controller_broker_heuristic: Heuristic = Heuristic.SHORTEST_EXPECTED
    """How the broker picks a stage's replica for a task."""
    controller_discover_replicas: bool = False
    """Resolve each replica URL's host to one URL per address (``--scale``)."""
    controller_discovery_interval_s: Annotated[float, Field(gt=0, le=3600)] = 10.0
    """Seconds between two resolutions of the replicas' host names."""
    controller_max_concurrent_searches: Annotated[int, Field(ge=1, le=1000)] = 4
    """Searches run at once; the others wait in the queue."""
    controller_default_max_iterations: Annotated[int, Field(ge=1, le=500)] = 40
    """Iterations of a search that gives no ``max_iterations``."""
    controller_view_spp: ViewSpp | None = 8
    """Samples per pixel of the views of searches submitted from now on (None: the renderer's
    default); each search records its own (``Search.view_settings``). 8 is the cheapest setting
    at which detection and search success did not drop (docs/RESULTS.md, ``--sweep``)."""
    controller_view_width: ViewWidth | None = None
    """Film width of the views of searches submitted from now on (the renderer keeps the
    scene's aspect); None: the scene's own. ``cosmos bench --sweep`` measures what detection
    and searches lose."""
    controller_view_cache_bytes: Annotated[int, Field(ge=0)] = 64 * 1024 * 1024
    """Bytes of rendered views kept for the page (:class:`~services.controller.views.ViewStore`,
    least recently used out; 0: none kept, every view asked for is rendered again)."""
    controller_render_timeout_s: Annotated[float, Field(gt=0, le=600)] = 60.0
    """Seconds per call to a renderer."""
    controller_detect_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    """Seconds per call to a detector."""
    controller_optimize_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    """Seconds per call to an optimizer."""
    controller_connect_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    """Seconds to connect to a stage's replica."""
    controller_outage_budget_s: Annotated[float, Field(ge=0, le=3600)] = 60.0
    """How long a search waits for a stage that no replica serves to come back before it fails
    (0: it fails at once); a search failed so can be resumed (``POST /searches/{id}/retry``)."""
    controller_max_upload_bytes: Annotated[int, Field(ge=1024)] = DEFAULT_MAX_UPLOAD_BYTES
    """Request body limit of a submitted target, in bytes."""
    controller_body_budget_bytes: Annotated[int, Field(ge=1024)] | None = None
    """Request-body bytes held at once (:mod:`services.common.bodies`): a request waits for
    its declared length before its body is read. Bodies up to 1/16 of the upload limit count in
    a lane of their own, a quarter of this, so they never wait behind maximal uploads. None:
    four maximal uploads (192 MiB), which keep the loop and the decoder busy."""
    controller_body_wait_s: Annotated[float, Field(ge=0, le=300, allow_inf_nan=False)] = (
        DEFAULT_BODY_WAIT_S
    )
    """How long a request waits for its body's bytes before a 503 (``Retry-After``)."""
    controller_body_timeout_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = (
        DEFAULT_BODY_TIMEOUT_S
    )
    """Seconds a body may take to arrive, plus its bytes at the rate below."""
    controller_body_min_bytes_per_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = (
        DEFAULT_MIN_BYTES_PER_S
    )
    """A body must arrive within ``timeout_s + bytes / min_bytes_per_s`` of its admission, else
    408 and the connection is closed (a trickling client holds budget no longer)."""
    controller_max_image_pixels: Annotated[int, Field(ge=64)] = DEFAULT_MAX_IMAGE_PIXELS
    """Decoded width x height of a target, read from its header before decoding."""
    controller_max_image_side: Annotated[int, Field(ge=8)] = 8192
    """The longest side of a target image, in pixels."""
    controller_auth: bool = True
    """Whether the public API wants an API key (``Authorization: Bearer``). Off (``off``,
    ``false``, ``0``), anyone may submit, see and cancel every search: for development only."""
    controller_cors_origins: str = ""
    """Origins whose pages may call the API from a browser, comma-separated
    (``https://app.example.org``); none by default, ``*`` for any."""
    controller_quota_active_searches: Annotated[int, Field(ge=1, le=100_000)] = 8
    """Searches one key may have queued or running at once."""
    controller_quota_searches_per_minute: Annotated[int, Field(ge=1, le=100_000)] = 30
    """Searches one key may submit in any minute."""
    controller_quota_stored_bytes: Annotated[int, Field(ge=1024)] = 1024**3
    """Bytes of target images one key's searches may hold (a failed search's is deleted)."""
    controller_retention_s: Annotated[float, Field(gt=0)] = 7 * 24 * 3600.0
    """Seconds a finished search (succeeded, failed, cancelled) is kept, with its image and
    iterations, after it finished."""
    controller_retention_sweep_s: Annotated[float, Field(gt=0, le=86400)] = 600.0
    """How often expired searches are looked for and deleted."""

    @field_validator(
        "controller_renderer_urls", "controller_detector_urls", "controller_optimizer_urls"
    )
    @classmethod
    def _some_url(cls, value: str) -> str:
        urls = _urls(value)
        if not urls:
            raise ValueError("give at least one replica URL")
        for url in urls:
            if not url.startswith(("http://", "https://")):
                raise ValueError(f"{url!r} is not an http(s) URL")
        return value

    @field_validator("controller_cors_origins")
    @classmethod
    def _origins(cls, value: str) -> str:
        for origin in _urls(value):
            if origin == "*":
                continue
            scheme, _, rest = origin.partition("://")
            if scheme not in {"http", "https"} or not rest or "/" in rest:
                raise ValueError(
                    f"{origin!r} is not an origin: give scheme://host[:port] "
                    "(https://app.example.org), comma-separated, or *"
                )
        return value

    @model_validator(mode="after")
    def _a_maximal_upload_fits_the_body_budget(self) -> ControllerSettings:
        self.body_limits()  # raises ValueError, naming both numbers, when it does not
        return self

    def body_limits(self) -> BodyLimits:
        """How request bodies are bounded: size, bytes in flight, time."""
        return BodyLimits.for_limit(
            self.controller_max_upload_bytes,
            budget_bytes=self.controller_body_budget_bytes,
            wait_s=self.controller_body_wait_s,
            timeout_s=self.controller_body_timeout_s,
            min_bytes_per_s=self.controller_body_min_bytes_per_s,
        )

    def cors_origins(self) -> list[str]:
        """The origins allowed to call the API from a browser (none: no CORS headers at all)."""
        return _urls(self.controller_cors_origins)

    def pools(self) -> dict[str, list[str]]:
        """Replica URLs per stage."""
        return {
            "renderer": _urls(self.controller_renderer_urls),
            "detector": _urls(self.controller_detector_urls),
            "optimizer": _urls(self.controller_optimizer_urls),
        }

    def timeouts(self) -> dict[str, float]:
        return {
            "renderer": self.controller_render_timeout_s,
            "detector": self.controller_detect_timeout_s,
            "optimizer": self.controller_optimize_timeout_s,
        }
