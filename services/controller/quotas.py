"""Quotas per API key: searches queued or running at once, searches per minute, stored bytes.

A key over a limit gets 429 with ``Retry-After``, and a problem detail saying what to do. The
counts come from the store (they survive a restart), plus the submissions admitted but not yet
recorded: between admitting a search and recording it the route awaits the renderer and the
image's decoding, and a burst of requests from one key must not all pass the same check.
Admin keys have no quotas: they are the operator's.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from services.common.errors import PayloadTooLargeError, TooManyRequestsError
from services.controller.store import SearchStore, utcnow

__all__ = ["ACTIVE_RETRY_S", "Limits", "QuotaExceededError", "Quotas"]

WINDOW = timedelta(minutes=1)
"""The window of the searches-per-minute quota (sliding)."""

ACTIVE_RETRY_S = 5
"""``Retry-After`` when a key has too many searches queued or running (when one ends is not
known; a search takes seconds)."""


class QuotaExceededError(TooManyRequestsError):
    slug = "quota-exceeded"
    title = "Quota exceeded"

    def __init__(self, detail: str, retry_after_s: float, quota: str) -> None:
        seconds = max(1, math.ceil(retry_after_s))
        super().__init__(
            detail,
            headers={"Retry-After": str(seconds)},
            extra={"quota": quota, "retry_after_s": seconds},
        )


@dataclass(frozen=True)
class Limits:
    """Each key's limits (the controller's ``COSMOS_CONTROLLER_QUOTA_…`` settings)."""

    active_searches: int
    searches_per_minute: int
    stored_bytes: int
    retention_s: float
    """How long a finished search is kept: when stored bytes free up again."""


@dataclass
class _Pending:
    searches: int = 0
    image_bytes: int = 0
    times: list[datetime] = field(default_factory=list)


class Quotas:
    """Admits a key's new searches within its :class:`Limits`."""

    def __init__(self, store: SearchStore, limits: Limits) -> None:
        self.store = store
        self.limits = limits
        self._pending: dict[str, _Pending] = {}
        self._deleted: dict[str, list[datetime]] = {}  # creation times, within the window

    def deleted(self, owner: str, created_at: datetime) -> None:
        """``owner`` deleted a search created at ``created_at``: its bytes are freed, but
        within the window it still counts towards the searches per minute (else deleting would
        lift that quota). Kept in memory: a restart forgets at most a minute of them."""
        if created_at >= utcnow() - WINDOW:
            self._deleted.setdefault(owner, []).append(created_at)

    @contextmanager
    def admit(self, owner: str, image_bytes: int) -> Iterator[None]:
        """Admit a search of ``owner`` with a target image of ``image_bytes``, or raise
        :class:`QuotaExceededError`; the block records it (the admission counts until then)."""
        self.check(owner, image_bytes)
        pending = self._pending.setdefault(owner, _Pending())
        now = utcnow()
        pending.searches += 1
        pending.image_bytes += image_bytes
        pending.times.append(now)
        try:
            yield
        finally:
            pending.searches -= 1
            pending.image_bytes -= image_bytes
            pending.times.remove(now)
            if pending.searches == 0:
                del self._pending[owner]

    def check(self, owner: str, image_bytes: int) -> None:
        """Raise :class:`QuotaExceededError` if ``owner`` may not submit a search now."""
        limits = self.limits
        if image_bytes > limits.stored_bytes:
            raise PayloadTooLargeError(
                f"the image's {image_bytes} bytes exceed your key's storage quota of "
                f"{limits.stored_bytes} bytes; send a smaller image (PNG or JPEG at the scene's "
                "size is plenty)",
                field="image",
            )
        now = utcnow()
        pending = self._pending.get(owner, _Pending())
        usage = self.store.usage(owner, since=now - WINDOW)
        active = usage.active + pending.searches
        if active >= limits.active_searches:
            raise QuotaExceededError(
                f"your key has {active} searches queued or running, its limit; wait for one to "
                "finish (GET /searches/{id}/events) or cancel one (DELETE /searches/{id}), then "
                "submit again",
                ACTIVE_RETRY_S,
                "active_searches",
            )
        deleted = [t for t in self._deleted.pop(owner, []) if t >= now - WINDOW]
        if deleted:
            self._deleted[owner] = deleted
        recent = [t for t in pending.times if t >= now - WINDOW] + deleted
        if usage.first_recent is not None:
            recent.append(usage.first_recent)
        if usage.recent + len(pending.times) + len(deleted) >= limits.searches_per_minute:
            first = min(recent)
            raise QuotaExceededError(
                f"your key submitted {limits.searches_per_minute} searches in the last minute, "
                "its limit; submit again after Retry-After seconds",
                (first + WINDOW - now).total_seconds(),
                "searches_per_minute",
            )
        stored = usage.image_bytes + pending.image_bytes
        if stored + image_bytes > limits.stored_bytes:
            retention = timedelta(seconds=limits.retention_s)
            frees = usage.first_expiry + retention if usage.first_expiry is not None else None
            wait = (frees - now).total_seconds() if frees is not None else limits.retention_s
            raise QuotaExceededError(
                f"your key's searches hold {stored} bytes of target images and this one adds "
                f"{image_bytes}, over its quota of {limits.stored_bytes}; finished searches are "
                f"deleted {limits.retention_s:.0f} s after they finish, which frees their images "
                "(the first after Retry-After seconds); delete finished or cancelled ones "
                "yourself (DELETE /searches/{id}), or send smaller images",
                wait,
                "stored_bytes",
            )
