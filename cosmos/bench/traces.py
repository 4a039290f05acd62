"""Why a search missed: its trace, read from the search's JSON as the controller answered it.

A trace says whether the search ever rendered the true grid pose, at which iteration (1 = the
start view), what the optimizer said there (its ``reason``, and ``match`` where the optimizer
reports one) and how many objects were detected there against the target's; then how the search
ended (status, the result's reason or the error). It reads the JSON, not the shared models, so
that fields newer than this bench (``confirmed``, ``match``) are read when present and a
recorded search of an older controller still parses.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from services.common.base import FrozenModel
from services.common.geometry.pose import GridIndex

__all__ = ["FailureTrace", "confirmed_of", "failure_trace"]


class FailureTrace(FrozenModel):
    """One missed (or unconfirmed) search, explained."""

    truth_visited: bool
    visit_iteration: int | None = None
    """1-based iteration at which the true grid pose was first rendered."""
    visit_reason: str | None = None
    visit_match: Any = None
    visit_detections: int | None = None
    target_detections: int | None = None
    visit_labels: tuple[str, ...] = ()
    target_labels: tuple[str, ...] = ()
    iterations: int = 0
    status: str
    final_reason: str = ""
    found: GridIndex | None = None
    confirmed: bool | None = None


def _index(pose: Mapping[str, Any] | None) -> GridIndex | None:
    if not pose or "index" not in pose:
        return None
    return GridIndex.model_validate(pose["index"])


def _labels(detections: Any) -> tuple[str, ...]:
    return tuple(sorted(str(d.get("label", "?")) for d in detections or ()))


def confirmed_of(search: Mapping[str, Any]) -> bool | None:
    """The result's ``confirmed`` flag: ``None`` without a result, ``True`` when the controller
    does not say (it confirmed every answer before it could give any-time ones)."""
    result = search.get("result")
    if not result:
        return None
    return bool(result.get("confirmed", True))


def failure_trace(search: Mapping[str, Any], truth: GridIndex) -> FailureTrace:
    """The trace of ``search`` (``GET /searches/{id}``'s JSON) against the true grid pose."""
    iterations = list(search.get("iterations") or ())
    target = search.get("target_detections")
    visit = next((i for i, it in enumerate(iterations) if _index(it.get("pose")) == truth), None)
    result = search.get("result") or {}
    error = search.get("error") or {}
    final_reason = str(
        result.get("reason")
        or error.get("detail")
        or (iterations[-1].get("reason") if iterations else "")
        or ""
    )
    fields: dict[str, Any] = {}
    if visit is not None:
        it = iterations[visit]
        fields = {
            "visit_iteration": visit + 1,
            "visit_reason": str(it.get("reason", "")),
            "visit_match": it.get("match"),
            "visit_detections": len(it.get("detections") or ()),
            "visit_labels": _labels(it.get("detections")),
        }
    return FailureTrace(
        truth_visited=visit is not None,
        target_detections=len(target) if target is not None else None,
        target_labels=_labels(target),
        iterations=len(iterations),
        status=str(search.get("status", "")),
        final_reason=final_reason,
        found=_index(result.get("pose")),
        confirmed=confirmed_of(search),
        **fields,
    )
