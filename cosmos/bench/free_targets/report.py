"""The baseline, the box-only bound and the box solver on a set of free targets, their table per
elevation band, and the solver's own table: its statuses and its confirmed-wrong answers."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final, Literal

import numpy as np

from cosmos.bench.free_targets.dense import dense_method, run_dense
from cosmos.bench.free_targets.draw import BANDS, FREE_VARIANTS, FreeTarget
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import (
    THRESHOLDS,
    ErrorSummary,
    PoseError,
    pose_error,
    summarize,
)
from cosmos.bench.free_targets.rendering import Renderer
from cosmos.bench.free_targets.shapes import SceneShapes
from cosmos.bench.free_targets.solve import baseline, box_only_bound
from cosmos.bench.free_targets.solver import (
    SOLVER,
    WRONG,
    WRONG_LOOSE,
    answer_estimate,
    confirmed_wrong,
    solve_target,
)
from cosmos.bench.tables import plain_table
from services.optimizer.free import SceneObjects

__all__ = [
    "METHODS",
    "TargetResult",
    "dense_line",
    "number_cell",
    "percent_cell",
    "evaluate",
    "group_rows",
    "solver_table",
    "text_table",
]

METHODS: Final = ("baseline", "box-only bound", SOLVER, *(dense_method(v) for v in FREE_VARIANTS))
Grouping = Literal["band", "objects", "given"]


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
    status: str | None = field(default=None)
    """The box solver's answer status (None when it did not run)."""
    renders: int = 0
    """Renders the dense stage spent (0 when it did not run or the renderer refused the pose)."""
    dense_ms: float = 0.0
    """The dense refinements' wall time over all image variants, renders left out."""
    dense_call_ms: tuple[float, ...] = ()
    """Each dense refinement's wall time (ms)."""

    @property
    def given(self) -> str:
        """Whether the target gave its intrinsics, as a table key."""
        return "K given" if self.intrinsics_given else "K estimated"


def evaluate(
    targets: Sequence[FreeTarget],
    shapes: SceneShapes,
    radius: float,
    seed: int,
    objects: SceneObjects | None = None,
    renderer: Renderer | None = None,
    *,
    spp: int = 16,
    renders: int = 1,
) -> list[TargetResult]:
    """The baseline, the box-only bound and, given the scene's ``objects``, the box solver
    (their noise seeded by ``seed`` and the target's index) on every target, against its true
    camera; given a ``renderer`` too, the dense stage after the box solver
    (:func:`~.dense.run_dense`, ``renders`` renders at ``spp``)."""
    results = []
    for target in targets:
        camera = target.annotations.camera
        truth = Estimate.of_camera(target.camera, camera.fov_deg, camera.width)
        rng = np.random.default_rng([seed, target.index, 1])
        estimates = {
            "baseline": baseline(target),
            "box-only bound": box_only_bound(target, shapes, rng),
        }
        status, spent, dense_ms = None, 0, 0.0
        call_ms: tuple[float, ...] = ()
        if objects is not None:
            answer = solve_target(target, objects, np.random.default_rng([seed, target.index, 2]))
            estimates[SOLVER] = answer_estimate(answer)
            status = answer.status
            if renderer is not None:
                dense = run_dense(
                    target,
                    answer,
                    renderer,
                    seed,
                    spp=spp,
                    renders=renders,
                    scene_fov_deg=objects.fov_deg,
                )
                estimates.update(dense.estimates)
                spent, dense_ms, call_ms = dense.renders, dense.refine_ms, dense.call_ms
        results.append(
            TargetResult(
                scene=target.scene,
                index=target.index,
                band=target.band,
                intrinsics_given=target.intrinsics_given,
                objects=len(target.usable),
                errors={name: pose_error(e, truth, radius) for name, e in estimates.items()},
                status=status,
                renders=spent,
                dense_ms=dense_ms,
                dense_call_ms=call_ms,
            )
        )
    return results


def group_rows(
    results: Sequence[TargetResult], method: str, by: Grouping = "band"
) -> list[tuple[str, ErrorSummary]]:
    """``method``'s summary per elevation band (or per count of objects in view, or whether the
    target gave its intrinsics) that has targets, then for all of them."""
    keys: list[str]
    if by == "band":
        keys = list(BANDS)
    elif by == "objects":
        keys = [str(n) for n in sorted({r.objects for r in results})]
    else:
        keys = ["K given", "K estimated"]
    rows: list[tuple[str, ErrorSummary]] = []
    for key in keys:
        errors = [
            r.errors[method] for r in results if str(getattr(r, by)) == key and method in r.errors
        ]
        if errors:
            rows.append((key, summarize(errors)))
    rows.append(("all", summarize([r.errors[method] for r in results if method in r.errors])))
    return rows


def percent_cell(value: float) -> str:
    """A share as a table cell (— when there is none)."""
    return "—" if math.isnan(value) else f"{value:.0%}"


def number_cell(value: float, digits: int) -> str:
    """A figure as a table cell (— when there is none, ∞ for a miss)."""
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
    "fov med %",
    "no pose",
)


def text_table(
    results: Sequence[TargetResult],
    by: Grouping = "band",
    totals_only: bool = False,
) -> str:
    """Per scene, per method, per elevation band (or count of objects at least 60 % visible;
    only the "all" row with ``totals_only``): the shares within the thresholds, median and p95
    position error (in % of the radius) and rotation error, and the targets without a pose. A
    method no target ran is left out."""
    rows = []
    for scene in dict.fromkeys(r.scene for r in results):
        mine = [r for r in results if r.scene == scene]
        for method in METHODS:
            if not any(method in r.errors for r in mine):
                continue
            for band, s in group_rows(mine, method, by):
                if totals_only and band != "all":
                    continue
                rows.append(
                    [
                        scene,
                        method,
                        band,
                        str(s.count),
                        *(percent_cell(w) for w in s.within),
                        number_cell(100 * s.position_median, 1),
                        number_cell(100 * s.position_p95, 1),
                        number_cell(s.rotation_median_deg, 2),
                        number_cell(s.rotation_p95_deg, 2),
                        number_cell(s.fov_median_pct, 2),
                        str(s.missed),
                    ]
                )
    header = list(HEADER)
    header.insert(2, {"band": "band", "objects": "objects", "given": "intrinsics"}[by])
    return plain_table(header, rows)


STATUSES: Final = ("found", "ambiguous", "failed")
SOLVER_HEADER: Final = (
    "scene",
    "band",
    "n",
    "found",
    "ambiguous",
    "failed",
    f"wrong >{WRONG[0]:.0%}/{WRONG[1]:g}°",
    "of them no K",
    f"found >{WRONG_LOOSE[0]:.0%}/{WRONG_LOOSE[1]:g}°",
    "fov med % (no K)",
    "n no K",
)


def solver_table(results: Sequence[TargetResult]) -> str:
    """The box solver per scene and elevation band: the shares of its statuses, how many
    ``found`` answers are confirmed wrong (outside :data:`~.solver.WRONG`; the number to keep
    at 0) and how many of those gave no intrinsics, how many are outside
    :data:`~.solver.WRONG_LOOSE`, and the median fov error over the targets that do not give
    their intrinsics."""
    rows = []
    ran = [r for r in results if SOLVER in r.errors]
    for scene in dict.fromkeys(r.scene for r in ran):
        mine = [r for r in ran if r.scene == scene]
        for band in [*BANDS, "all"]:
            group = [r for r in mine if band in ("all", r.band)]
            if not group:
                continue
            errors = [r.errors[SOLVER] for r in group]
            statuses = [r.status for r in group]
            unknown = [r.errors[SOLVER].fov_pct for r in group if not r.intrinsics_given]
            rows.append(
                [
                    scene,
                    band,
                    str(len(group)),
                    *(percent_cell(statuses.count(s) / len(group)) for s in STATUSES),
                    str(confirmed_wrong(errors, statuses)),
                    str(
                        confirmed_wrong(
                            [r.errors[SOLVER] for r in group if not r.intrinsics_given],
                            [r.status for r in group if not r.intrinsics_given],
                        )
                    ),
                    str(confirmed_wrong(errors, statuses, WRONG_LOOSE)),
                    number_cell(float(np.median(unknown)) if unknown else math.nan, 1),
                    str(len(unknown)),
                ]
            )
    return plain_table(list(SOLVER_HEADER), rows)


def dense_line(results: Sequence[TargetResult]) -> str:
    """The dense stage's cost: renders per search (median, max), refinement time per target
    and image variant (median, ms), and per call of the refinement with the intrinsics given
    and estimated (median and p95, ms)."""
    ran = [r for r in results if r.dense_ms > 0.0]
    if not ran:
        return "dense: no target refined"
    renders = [r.renders for r in results]
    per_variant = [r.dense_ms / len(FREE_VARIANTS) for r in ran]
    return (
        f"dense: renders per search median {np.median(renders):g}, max {max(renders)}; "
        f"refinement median {np.median(per_variant):.0f} ms (p95 "
        f"{np.percentile(per_variant, 95):.0f} ms) per target and image variant"
    ) + "".join(
        f"; per call, {key}: median {np.median(calls):.0f} ms, p95 "
        f"{np.percentile(calls, 95):.0f} ms ({len(calls)} calls)"
        for key in ("K given", "K estimated")
        if (calls := [ms for r in ran if r.given == key for ms in r.dense_call_ms])
    )
