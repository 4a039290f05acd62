"""The baseline and the box-only bound on a set of free targets, and their table per elevation
band."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np

from cosmos.bench.free_targets.draw import BANDS, FreeTarget
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import (
    THRESHOLDS,
    ErrorSummary,
    PoseError,
    pose_error,
    summarize,
)
from cosmos.bench.free_targets.shapes import SceneShapes
from cosmos.bench.free_targets.solve import baseline, box_only_bound
from cosmos.bench.tables import plain_table

__all__ = ["METHODS", "TargetResult", "evaluate", "group_rows", "text_table"]

METHODS: Final = ("baseline", "box-only bound")


@dataclass(frozen=True)
class TargetResult:
    """One target's errors under each reference method."""

    scene: str
    index: int
    band: str
    intrinsics_given: bool
    objects: int
    """How many objects the target shows at least 60 % visible."""
    errors: dict[str, PoseError]


def evaluate(
    targets: Sequence[FreeTarget], shapes: SceneShapes, radius: float, seed: int
) -> list[TargetResult]:
    """The baseline and the box-only bound (its noise seeded by ``seed`` and the target's
    index) on every target, against its true camera."""
    results = []
    for target in targets:
        camera = target.annotations.camera
        truth = Estimate.of_camera(target.camera, camera.fov_deg, camera.width)
        rng = np.random.default_rng([seed, target.index, 1])
        estimates = {
            "baseline": baseline(target),
            "box-only bound": box_only_bound(target, shapes, rng),
        }
        results.append(
            TargetResult(
                scene=target.scene,
                index=target.index,
                band=target.band,
                intrinsics_given=target.intrinsics_given,
                objects=len(target.usable),
                errors={name: pose_error(e, truth, radius) for name, e in estimates.items()},
            )
        )
    return results


def group_rows(
    results: Sequence[TargetResult], method: str, by: Literal["band", "objects"] = "band"
) -> list[tuple[str, ErrorSummary]]:
    """``method``'s summary per elevation band (or per count of objects in view) that has
    targets, then for all of them."""
    keys: list[str] = list(BANDS) if by == "band" else sorted({str(r.objects) for r in results})
    rows: list[tuple[str, ErrorSummary]] = []
    for key in keys:
        errors = [r.errors[method] for r in results if str(getattr(r, by)) == key]
        if errors:
            rows.append((key, summarize(errors)))
    rows.append(("all", summarize([r.errors[method] for r in results])))
    return rows


def _pct(value: float) -> str:
    return "—" if math.isnan(value) else f"{value:.0%}"


def _num(value: float, digits: int) -> str:
    if math.isnan(value):
        return "—"
    return "∞" if math.isinf(value) else f"{value:.{digits}f}"


HEADER: Final = (
    "scene",
    "method",
    "n",
    *(f"≤{p:.0%}/{r:g}°" for p, r in THRESHOLDS),
    "pos med %r",
    "pos p95 %r",
    "rot med °",
    "rot p95 °",
    "no pose",
)


def text_table(results: Sequence[TargetResult], by: Literal["band", "objects"] = "band") -> str:
    """Per scene, per method, per elevation band (or count of objects at least 60 % visible):
    the shares within the thresholds, median and p95 position error (in % of the radius) and
    rotation error, and the targets without a pose."""
    rows = []
    for scene in dict.fromkeys(r.scene for r in results):
        mine = [r for r in results if r.scene == scene]
        for method in METHODS:
            for band, s in group_rows(mine, method, by):
                rows.append(
                    [
                        scene,
                        method,
                        band,
                        str(s.count),
                        *(_pct(w) for w in s.within),
                        _num(100 * s.position_median, 1),
                        _num(100 * s.position_p95, 1),
                        _num(s.rotation_median_deg, 2),
                        _num(s.rotation_p95_deg, 2),
                        str(s.missed),
                    ]
                )
    header = list(HEADER)
    header.insert(2, "band" if by == "band" else "objects")
    return plain_table(header, rows)
