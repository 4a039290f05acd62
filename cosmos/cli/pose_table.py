"""Searches' answers as rows of a CSV table, one per photo (``cosmos search … --poses FILE``): what
a survey's camera list holds, for a GIS or a photogrammetry tool to read.

A free search's row holds its answer camera: the centre ``(x, y, z)`` in scene units, the
orientation as a quaternion ``(w, x, y, z)`` (camera to world) and as yaw/pitch/roll in degrees,
and the intrinsics used (fov, ``fx fy cx cy`` in the photo's pixels) with where they came from.
Both kinds give the hemisphere pose (``theta_deg``, ``phi_deg``: a free answer's nearest grid
pose, a hemisphere search's refined pose). A photo that was not searched (unreadable, or refused
by the controller) keeps its row: ``status`` says so and ``reason`` why, the pose left empty.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Final

from services.common.contracts.search import Search

__all__ = ["COLUMNS", "Row", "not_searched", "row_of", "write_rows"]

COLUMNS: Final = (
    "image",
    "search_id",
    "status",
    "answer",
    "confirmed",
    "x",
    "y",
    "z",
    "qw",
    "qx",
    "qy",
    "qz",
    "yaw_deg",
    "pitch_deg",
    "roll_deg",
    "fov_deg",
    "fx_px",
    "fy_px",
    "cx_px",
    "cy_px",
    "intrinsics",
    "theta_deg",
    "phi_deg",
    "renders",
    "confidence",
    "reason",
)
"""The table's header; ``status`` is the search's (``succeeded``, ``failed``, ``cancelled``) or
``not searched``; ``answer`` is ``found``, ``ambiguous`` or ``failed`` (a hemisphere search:
``found`` or ``not confirmed``)."""

Row = Mapping[str, str | int | float | bool]
"""One photo's row, by :data:`COLUMNS` (those left out are empty)."""


def row_of(image: str, search: Search) -> Row:
    """``image``'s row from its finished ``search`` (module docstring)."""
    row: dict[str, str | int | float | bool] = {
        "image": image,
        "search_id": search.id,
        "status": search.status,
    }
    result = search.result
    if result is None:
        row["answer"] = "failed"
        error = search.error
        row["reason"] = (error.detail or error.title) if error is not None else ""
        return row
    row.update(
        confirmed=result.confirmed,
        renders=result.renders,
        confidence=round(result.confidence, 4),
        reason=result.reason,
        theta_deg=round(result.refined_pose.theta_deg, 4),
        phi_deg=round(result.refined_pose.phi_deg, 4),
    )
    free = result.free
    if free is None:
        row["answer"] = "found" if result.confirmed else "not confirmed"
        return row
    pose, k = free.pose, free.pose.intrinsics
    row.update(zip(("x", "y", "z"), (round(v, 6) for v in pose.position), strict=True))
    row.update(
        zip(("qw", "qx", "qy", "qz"), (round(v, 8) for v in pose.quaternion_wxyz), strict=True)
    )
    angles = ("yaw_deg", "pitch_deg", "roll_deg")
    row.update(zip(angles, (round(v, 4) for v in pose.yaw_pitch_roll_deg), strict=True))
    row.update(
        answer=free.status,
        fov_deg=round(k.fov_deg, 4),
        fx_px=round(k.fx_px, 3),
        fy_px=round(k.fy_px, 3),
        cx_px=round(k.cx_px, 3),
        cy_px=round(k.cy_px, 3),
        intrinsics=k.source,
        theta_deg=round(free.nearest_grid.theta_deg, 4),
        phi_deg=round(free.nearest_grid.phi_deg, 4),
    )
    return row


def not_searched(image: str, why: str) -> Row:
    """The row of a photo that no search was made for, and ``why``."""
    return {"image": image, "status": "not searched", "reason": why}


def write_rows(path: Path, rows: Iterable[Row]) -> None:
    """The ``rows`` as a CSV table at ``path``, under the :data:`COLUMNS` header."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as out:
        table = csv.DictWriter(out, fieldnames=COLUMNS)
        table.writeheader()
        table.writerows(rows)
