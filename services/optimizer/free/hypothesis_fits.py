"""Each hypothesis' edge fits: its pairs fitted, re-drawn at the fitted pose and fitted again.

A hypothesis is a start pose and its pairs (detection ``i`` ↔ object ``j``). Its fit is PnP on
the paired box centres corrected for the box-centre bias (:func:`.refine.centre_pnp`), then
least squares on the box edges (:func:`.refine.refine_edges`). The pairs are then re-drawn at
the fitted pose: a Hungarian assignment on the masked edge RMS of the clipped projected boxes,
gated by :func:`.tolerances.inlier_gate`; when they changed, the fit is run again on them.

Without given intrinsics and with at least :data:`MIN_FOCAL_PAIRS` pairs the focal length joins
every hypothesis' edge fit, started from the scene camera's; the :data:`FOCAL_WIDENED` best of
those fits (least :func:`.tolerances.truncated_cost`) are also started from the other zooms of
:data:`FOCAL_STARTS`, the least RMS kept. Every hypothesis gets the focal: a fixed-focal fit is
a dolly zoom of the free one (farther and narrower), which at noise-level residuals would pass
for a rival. The focal length stays within the lenses considered (:attr:`EdgeFits.focal_range`:
:class:`~.focal_bounds.FocalRange`) from whatever fit it starts, and a refined fit that ends on
a bound keeps the scene camera's (:func:`refined`).

Different hypotheses often come to the same pairs and the same centre-PnP pose, and the edge
fit from there is the same least-squares problem from the same start: :class:`EdgeFits` fits it
once (:data:`SAME_START_POSITION`, :data:`SAME_START_DEG`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.optimizer.free.answer import IntrinsicsSource
from services.optimizer.free.focal_bounds import FocalRange, at_bound
from services.optimizer.free.hypotheses import pose_distance
from services.optimizer.free.objects import SceneObjects, project_boxes
from services.optimizer.free.refine import Intrinsics, PoseFit, centre_pnp, refine_edges
from services.optimizer.free.tolerances import inlier_gate, truncated_cost
from services.optimizer.geometry import FloatArray
from services.optimizer.matching import assign

__all__ = [
    "FOCAL_STARTS",
    "FOCAL_WIDENED",
    "LOOSE_PAIR_RATIO",
    "MIN_FOCAL_PAIRS",
    "EdgeFits",
    "Fit",
    "Start",
    "focal_fits",
    "left_out",
    "refined",
]

MIN_FOCAL_PAIRS: Final = 4
FOCAL_STARTS: Final = (0.75, 1.0, 1.33)
"""Zooms of the scene camera's focal length the joint pose-and-focal fit starts from."""
FOCAL_WIDENED: Final = 1
"""Hypotheses whose focal fit also starts from the other :data:`FOCAL_STARTS` (the best by
:func:`.tolerances.truncated_cost` of their fits from the scene camera's focal; measured when
the best was the one with the most pairs, then the least RMS). Every hypothesis from every start
spent two thirds of a solve without intrinsics; yet with 0, 1 or 2 widened every answer (status,
pose to 1e-3 units and 0.05°, fov to 0.02°) was the one all starts gave, on the 16 cameras of
``tests/optimizer/test_free_pose.py`` (own and general labels) and the free targets of ``python
-m cosmos.bench.free_targets --scene demo --random-scenes 2 --n 8 --seed 1`` (9 without
intrinsics). One keeps the other zooms for the pose that will be answered; the solve without
intrinsics took 0.6-0.7 times as long."""
LOOSE_PAIR_RATIO: Final = 0.5
"""A pair whose edge RMS reaches this share of its gate is refitted without (:func:`left_out`)."""
SAME_START_POSITION: Final = 1e-3
"""Centre-PnP starts whose camera centres are this close (a fraction of the scene radius) ..."""
SAME_START_DEG: Final = 0.05
"""... and whose rotations are this close, with the same pairs and intrinsics, share one edge
fit. Measured on the free targets of seed 1 (demo, garden, two generated scenes) and seed 5 (two
generated), 96 solves with the fov given and not, one run after the other: every answer stayed
the same (status, alternatives; pose and fov within 6e-5 units and degrees), and a solve took
0.62 times as long on demo (82 → 51 ms), 0.68 on garden (47 → 32 ms) and 0.87-0.97 on the
generated scenes, where the general model's many hypotheses pair differently."""

Start = tuple[FloatArray, FloatArray, NDArray[np.intp], NDArray[np.intp]]
"""A hypothesis: world-to-camera ``(rvec, tvec)``, its detections and their objects."""


@dataclass(frozen=True)
class Fit:
    """A hypothesis' edge fit on its (re-drawn) pairs, and where its intrinsics come from."""

    fit: PoseFit
    detections: NDArray[np.intp]
    objects: NDArray[np.intp]
    source: IntrinsicsSource

    @property
    def key(self) -> tuple[FloatArray, FloatArray]:
        """The fitted pose, world-to-camera ``(rvec, tvec)``."""
        return self.fit.rvec, self.fit.tvec


@dataclass
class EdgeFits:
    """One solve's edge fits of paired boxes: ``boxes`` (n, 4) in pixels, their clipped-side
    ``masks``, against ``objects``; a fit from a start already fitted is the one made then."""

    objects: SceneObjects
    boxes: FloatArray
    masks: NDArray[np.bool_]
    focal_range: FocalRange | None = None
    """The focal lengths (pixels) a fitted one stays within, whatever fit it starts from
    (:class:`~.focal_bounds.FocalRange`; by default within :data:`~.focal_bounds.FOCAL_BOUNDS`
    of the scene camera's)."""
    _made: list[tuple[tuple[object, ...], tuple[FloatArray, FloatArray], PoseFit]] = field(
        default_factory=list, init=False, repr=False
    )
    """Each fit made: its problem (pairs, focal fitted, intrinsics), its start, the fit."""

    def fit(
        self,
        dets: NDArray[np.intp],
        objs: NDArray[np.intp],
        rvec: FloatArray,
        tvec: FloatArray,
        intrinsics: Intrinsics,
        fit_focal: bool,
    ) -> PoseFit:
        """Centre PnP from ``(rvec, tvec)`` on the pairs ``dets`` ↔ ``objs``, then the edge fit
        (the focal too with ``fit_focal``)."""
        paired = self.objects.subset(objs)
        b, m = self.boxes[dets], self.masks[dets]
        start = centre_pnp(paired, b, m, rvec, tvec, intrinsics)
        problem = (
            tuple(sorted(zip(dets.tolist(), objs.tolist(), strict=True))),
            fit_focal,
            (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy),
        )
        for made_problem, made_start, made in self._made:
            if made_problem == problem and self._same(made_start, start):
                return made
        fitted = refine_edges(
            paired,
            b,
            m,
            *start,
            intrinsics,
            fit_focal=fit_focal,
            focal_range=self.focal_range,
        )
        self._made.append((problem, start, fitted))
        return fitted

    def _same(self, a: tuple[FloatArray, FloatArray], b: tuple[FloatArray, FloatArray]) -> bool:
        moved, turned = pose_distance(a, b)
        return moved <= SAME_START_POSITION * self.objects.radius and turned <= SAME_START_DEG

    def bounds(self, scene: Intrinsics) -> FocalRange:
        """The focal lengths a fit may take: :attr:`focal_range`, else within
        :data:`~.focal_bounds.FOCAL_BOUNDS` of the ``scene`` camera's."""
        return FocalRange.about(scene.fx) if self.focal_range is None else self.focal_range


def reassign(
    fits: EdgeFits,
    compatible: NDArray[np.bool_],
    fit: PoseFit,
    width: float,
    height: float,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pairs at a fitted pose: gated Hungarian on the masked edge RMS of the clipped boxes."""
    k = fit.intrinsics
    projected = project_boxes(fits.objects, fit.rotation(), fit.tvec, (k.fx, k.fy), (k.cx, k.cy))
    projected = np.clip(projected, 0.0, [width, height, width, height])
    boxes, masks = fits.boxes, fits.masks
    diff = (boxes[:, np.newaxis, :] - projected[np.newaxis, :, :]) ** 2
    diff[np.broadcast_to(masks[:, np.newaxis, :], diff.shape)] = 0.0
    used = np.maximum((~masks).sum(axis=1), 1)[:, np.newaxis]
    cost = np.sqrt(diff.sum(axis=-1) / used) / inlier_gate(boxes)[:, np.newaxis]
    cost[~compatible] = np.inf
    pairs = assign(cost, 1.0)
    return pairs.rows, pairs.cols


def focal_fits(
    fits: EdgeFits, starts: Sequence[Start], intrinsics: Intrinsics, estimate_focal: bool
) -> list[tuple[PoseFit, bool]]:
    """Each hypothesis' first edge fit, and whether its focal length was fitted (module
    docstring)."""
    firsts = []
    for rvec, tvec, dets, objs in starts:
        focal = estimate_focal and len(dets) >= MIN_FOCAL_PAIRS
        firsts.append((fits.fit(dets, objs, rvec, tvec, intrinsics, focal), focal))
    gates = inlier_gate(fits.boxes)
    order = sorted(
        range(len(firsts)),
        key=lambda i: (truncated_cost(firsts[i][0], starts[i][2], gates), -len(starts[i][2])),
    )
    for i in [i for i in order if firsts[i][1]][:FOCAL_WIDENED]:
        rvec, tvec, dets, objs = starts[i]
        others = [
            fits.fit(dets, objs, rvec, tvec, intrinsics.scaled(s), True)
            for s in FOCAL_STARTS
            if s != 1.0
        ]
        firsts[i] = (min([firsts[i][0], *others], key=lambda f: f.rms_px), True)
    return firsts


def refined(
    fits: EdgeFits,
    compatible: NDArray[np.bool_],
    first: tuple[PoseFit, bool],
    pairs: tuple[NDArray[np.intp], NDArray[np.intp]],
    intrinsics: Intrinsics,
    size: tuple[float, float],
) -> Fit | None:
    """A hypothesis' first fit (:func:`focal_fits`, on the hypothesis' ``pairs``) with its
    pairs re-drawn and its edges refitted; None when the refined pose pairs no detection at all.
    When the pairs come back as they were and the focal length was not fitted, the first fit
    stands: it has converged on them already, a refit only moves it within the fit's tolerance
    (with the focal fitted it can go on from where the first fit's bounded steps stopped, and
    does)."""
    fit, focal = first
    dets, objs = reassign(fits, compatible, fit, *size)
    if len(dets) == 0:
        return None
    estimated = focal and len(dets) >= MIN_FOCAL_PAIRS
    if not focal and _same_pairs((dets, objs), pairs):
        return Fit(fit=fit, detections=pairs[0], objects=pairs[1], source="scene")
    # Too few pairs left to hold the focal length: back to the scene camera's.
    k = fit.intrinsics if estimated or not focal else intrinsics
    if len(dets) >= 3:
        fit = fits.fit(dets, objs, fit.rvec, fit.tvec, k, estimated)
        if estimated and at_bound(fit.intrinsics.fx, fits.bounds(intrinsics)):
            # The boxes would take the focal further than it may go: they do not pin it.
            fit = fits.fit(dets, objs, fit.rvec, fit.tvec, intrinsics, False)
            estimated = False
    else:
        paired = fits.objects.subset(objs)
        fit = refine_edges(paired, fits.boxes[dets], fits.masks[dets], fit.rvec, fit.tvec, k)
    return Fit(fit=fit, detections=dets, objects=objs, source="estimated" if estimated else "scene")


def _same_pairs(
    a: tuple[NDArray[np.intp], NDArray[np.intp]], b: tuple[NDArray[np.intp], NDArray[np.intp]]
) -> bool:
    """Whether two pairings ``(detections, objects)`` pair the same detections with the same
    objects, in any order."""

    def pairs(p: tuple[NDArray[np.intp], NDArray[np.intp]]) -> list[tuple[int, int]]:
        return sorted(zip(p[0].tolist(), p[1].tolist(), strict=True))

    return pairs(a) == pairs(b)


def left_out(
    fits: EdgeFits,
    compatible: NDArray[np.bool_],
    best: Fit,
    intrinsics: Intrinsics,
    size: tuple[float, float],
) -> list[Fit]:
    """``best`` refitted from its own pose without each of its loose pairs in turn (edge RMS
    at least :data:`LOOSE_PAIR_RATIO` of its :func:`inlier_gate`), the pairs then re-drawn
    (:func:`refined`): those refits that explain the boxes better than ``best`` (less
    :func:`truncated_cost`); none with fewer than four pairs (three must stay).

    A box that no longer lies where the scene file puts its object (an object moved since the
    scene was modelled) pulls a fit that pairs it, and the other boxes' residuals grow with
    it: the worst pair need not be the moved one. Its minimal sets without that box may all
    land in the other basin of a flip, so no hypothesis of its own starts near the truth.
    Replayed on the detections of ten ``cosmos bench --free`` runs (seeds 1–5, 1,200 targets,
    ``benchmarks.free_replay``): 3 more box estimates within 5 %/2° (a demo view whose moved
    ball had pulled the pose 18 % off, now 0.3 %), none fewer; 2 more and 1 fewer within
    10 %/5°; the solves 3 % slower in all. Only the better refits are kept: keeping all, one
    through the stack crowded out the alternative that its search had answered 0.1 % off
    (seed 5, the general model), which then answered 218 % off."""
    if len(best.detections) < 4:
        return []
    gates = inlier_gate(fits.boxes)
    ratio = best.fit.pair_rms_px / gates[best.detections]
    bar = truncated_cost(best.fit, best.detections, gates)
    focal = best.source == "estimated"
    out = []
    for drop in np.flatnonzero(ratio >= LOOSE_PAIR_RATIO):
        keep = np.arange(len(ratio)) != drop
        dets, objs = best.detections[keep], best.objects[keep]
        estimate = focal and len(dets) >= MIN_FOCAL_PAIRS
        # Three pairs do not hold a focal length, and the one fitted with the dropped pair is
        # what that pair pulled: the scene camera's, as refined() goes back to it.
        k = best.fit.intrinsics if estimate else intrinsics
        first = fits.fit(dets, objs, best.fit.rvec, best.fit.tvec, k, estimate)
        fit = refined(fits, compatible, (first, estimate), (dets, objs), intrinsics, size)
        if fit is not None and truncated_cost(fit.fit, fit.detections, gates) < bar:
            out.append(fit)
    return out
