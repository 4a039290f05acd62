"""Dense refinement of a camera pose by one render: model-based edge alignment (issue 23).

A render at the estimated pose, with its per-pixel depth (the renderer's ``POST /render/depth``),
gives the model's edges as 3D points; the pose (and, without given intrinsics, the focal length)
is then fitted so that those points project onto the target image's edges, as model-based edge
tracking does (RAPiD, ViSP's moving edges), here with a chamfer cost over many edge pixels.

Model points
    Canny edges of the render (:func:`~.edges.image_edges`: the same detector as on the target,
    so both are located alike), with the render's outline (:func:`~.edges.outline`) only those
    near it: silhouettes, occlusions, creases and texture, not the shadows and terminators of
    the scene file's light, which a photo's light puts elsewhere. When most of those other
    edges already lie on the target's at the outline's fit (:data:`LIGHT_SHARE`: the target
    shares the render's light), they join one last fit at full resolution.
    Each edge pixel (u, v) (centre ``(j + ½, i + ½)``) goes back through the depth ``Z`` to
    the camera point ``X_c = Z (x, y, 1)`` with ``(x, y)`` its undistorted normalised
    coordinates, and to the world ``X = R₀ᵀ (X_c - t₀)``. ``Z`` is the smallest depth in the
    pixel's 3x3 neighbourhood: an edge at a silhouette belongs to the nearer, occluding
    surface. Each point keeps its edge orientation ``θ`` (the render's gradient direction,
    modulo π) (:func:`~.edges.edge_points`).

Target
    Canny edges of the target image at its own resolution, split into :data:`ORIENTATION_BINS`
    bins of orientation. For bin ``b`` the distance transform ``D_b`` (``cv2.distanceTransform``,
    exact Euclidean) is the distance to the nearest target edge whose orientation lies in bin
    ``b`` or a neighbour, truncated at ``τ``: an edge is matched only to edges running roughly
    the same way (oriented chamfer matching), which keeps clutter across it from pulling.

Fit
    With ``π(X; ω, t, k)`` OpenCV's projection (``cv2.projectPoints``, the lens included) of the
    pose ``X_c = R(ω) X + t`` (``ω`` a rotation vector) through the intrinsics with the focal
    lengths scaled by ``k`` (fixed at 1 when the intrinsics are given),

    .. math:: \\min_{ω, t, k} \\sum_i ρ_σ\\big(D_{b_i}(π(X_i; ω, t, k))^2\\big),
              \\qquad ρ_σ(z) = 2σ^2(\\sqrt{1 + z/σ^2} - 1)

    (soft-L1, ``scipy.optimize.least_squares``), ``D`` sampled bilinearly (sub-pixel), the
    Jacobian ``∂D/∂p = ∇D · ∂π/∂p`` from ``cv2.projectPoints``' own Jacobian and the
    distance transform's central differences. Coarse to fine (:data:`LEVELS`): the target
    downsampled by 4, then 2, then at full resolution, each level's distances in its own pixels,
    so that an estimate a few percent off (tens of pixels) lies within the first level's basin.
    After each level a start keeps the better of its fit and itself by the full-resolution
    cost, so a level that slips into a wrong basin (a tiled ground repeats) does no harm:
    measured on generated scenes, that turned 2 of 5 garden targets seen at 10–30° from 0.5 %
    off into 25–60 % off before.

    A coarse level fits an evenly spaced share of the points (:data:`LEVEL_POINTS`), and a
    level ends once its steps are far below a pixel (:data:`~.level_fit.X_TOLERANCE`). Without lens
    distortion the projection and its Jacobian are numpy's (``cv2.projectPoints`` always
    computes its 15-column Jacobian, ~17 times the projection alone, also for the residual
    evaluations that need none), and the Jacobian reuses the residuals' projection at the same
    pose. Together, per call on the free bench (:data:`LEVEL_POINTS`, seed 1, one run after
    the other): 559 → 245 ms median (p95 784 → 387) with the focal fitted, 113 → 70 ms (p95
    186 → 100) with the intrinsics given.

    ``least_squares`` solves its trust-region steps exactly (an SVD of the ``n x 6`` or
    ``n x 7`` Jacobian). LSMR was chosen first, on a report of ~35 ms per SVD under load;
    measured again (numpy 2.4, demo free targets of seed 1, ms per call, median), the pose
    alone took 75 ms with LSMR and 45 exact when idle, 67-85 and 52 with two busy processes on
    the two cores, landing on the same poses (to 0.02 units); the pose and focal 210 and 160 ms
    idle. Fits of the focal then land elsewhere along the dolly-zoom valley (below). Through the
    stack (``cosmos bench --free --scene demo --random-scenes 2 --n 8``, 27 targets without
    the fov on clean, JPEG and noise per seed, one run each way), exact steps took 27 of 27
    within 5 %/2° against 26 on seed 1 (median fov error 0.54 % against 0.47 %) and 14 against
    11 on seed 2 (3.7 % against 5.3 %), and the median search without the fov took 669 against
    840 ms (seed 1) and 1034 against 1224 ms (seed 2).

Unknown focal length
    Distance and focal length trade off along a long, flat valley (a dolly zoom), and the box
    estimate's fov is ~7 % off (median). The fit starts from :data:`ZOOM_STARTS`, each a dolly
    zoom of the estimate that keeps the points' median depth ``z̃`` in place (focal ``s f``,
    camera moved back by ``(s - 1) z̃``), carries every start through the levels and keeps the
    best. The fitted focal is kept unless the edges leave it loose (:data:`ZOOM_SIGMA`); then
    the estimate's focal stays and the pose alone is fitted (:attr:`DenseFit.focal_fitted`).
    So too when the fit ends outside the lenses considered (``focal_range``: a
    :class:`~.focal_bounds.FocalRange`), or on a bound: it is sought within them.
    The render's silhouettes and occlusions belong to its own viewpoint: when the fit moved far
    from it, most of the remaining focal error is that bias, and one more render at the fit
    and a refit remove it (:func:`~.refit.worth_another_render`; so too for a fit of the pose alone
    that moved far). Measured on the free targets of
    ``python -m cosmos.bench.free_targets --random-scenes 4 --n 24 --seed 1`` without given
    intrinsics: 75 % → 97 % within 5 % / 2°, median fov error 1.1 % → 0.9 %, at most 2 renders.
    The focal length is told from the distance by the perspective of the edges, a fraction of a
    pixel on a small photo: the controller then renders at up to twice the photo's size and the
    optimizer enlarges its grey to that film (``pixel`` = 2: :func:`pyramid` keeps every
    tolerance in the photo's pixels). ``python -m benchmarks.focal_valley --n 4 --seeds 21
    --random-scenes 1`` against the same with ``--scale 2 --enlarge`` (8 targets of demo and a
    generated scene, each fitted from renders 3 % off along the valley either way, one run):
    fits within 2 % of the true fov 3 → 11 of 16 (10–30° 2 → 4 of 4, 60–89° 1 → 4 of 8, nadir
    0 → 3 of 4); its wall at a zoom of 0.9 rose in every band.

Lens check
    The fit above is a pinhole's unless a lens is given. Asked for (``check_radial``), one more
    fit at full resolution from where it ended frees OpenCV's radial ``k1`` too, and the focal
    length unless it was given (:func:`radial_check`, with ``cv2.projectPoints``' Jacobian
    column of ``k1``): how far that bends the edges, and how surely, tells a distorted photo
    from a pinhole's (:mod:`services.optimizer.refine_pose` judges it). A lens given as a
    radial ``k1`` alone (one an earlier check estimated) may be checked the same way, ``k1``
    started from it.

The residual reported is the RMS of ``D`` over the points within :data:`INLIER_PX` of a target
edge at full resolution: a pose that explains the image leaves most points there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.contracts.free import above_chance
from services.common.geometry.camera import PinholeCamera, fov_deg_of
from services.common.geometry.free_camera import LensDistortion
from services.optimizer.free.chamfer import ChamferProblem
from services.optimizer.free.edges import (
    MAX_POINTS,
    ORIENTATION_BINS,
    EdgePoints,
    Level,
    edge_chance,
    edge_points,
    edge_points_by_outline,
)
from services.optimizer.free.focal_bounds import FocalRange, at_bound
from services.optimizer.free.lens_check import RadialCheck, radial_check
from services.optimizer.free.level_fit import (
    INLIER_PX,
    MIN_POINTS,
    fit_level,
    level_cost,
    parameter_sigma,
)
from services.optimizer.free.refine import Intrinsics
from services.optimizer.free.target_maps import TargetMaps
from services.optimizer.geometry import FloatArray

__all__ = [
    "INLIER_PX",
    "LEVELS",
    "FINE_START_SHARE",
    "LEVEL_POINTS",
    "ORIENTATION_BINS",
    "DenseFit",
    "EdgePoints",
    "edge_points",
    "pyramid",
    "radial_only",
    "refine_dense",
]

LEVELS: Final = ((4, 2.0, 8.0), (2, 1.5, 6.0), (1, 1.0, 5.0))
"""(downsampling factor, soft-L1 scale σ, truncation τ), both in pixels of the level, on a
film of the target's own pixels (:func:`pyramid` on an enlarged one)."""
LEVEL_POINTS: Final[tuple[int | None, ...]] = (1000, None, None)
"""Model edge points fitted at each level of :data:`LEVELS` (evenly spaced; None: all): the
first level's pixels are 4 times larger, and fewer points pin its pose as well. Measured with
:data:`~.level_fit.X_TOLERANCE` by ``python -m cosmos.bench.free_targets --scene demo
--random-scenes 3 --n 12 --seed S`` (S = 1, 3) against the former all points and ``xtol``
1e-8: no share within 2 %/1°, 5 %/2° or 10 %/5° lower, with the intrinsics given (identical)
or not (of 48 fits each, 28/46/48 → 31/48/48 and 18/34/43 → 19/34/43). (500, 1000, None) was
no faster but lost 2 fov-free fits of seed 3 at 10 %/5°; carrying only the best 2 zoom starts
into the last level saved a third more but lost one at seed 1 (the zoom is told apart at full
resolution only)."""
FINE_START_SHARE: Final = 0.85
"""A start whose render already leaves this share of its edge points (above chance) within
:data:`INLIER_PX` of the target's edges lies in the full-resolution basin: the pose alone is
then fitted at that level only, without the coarse ones (nor their distance maps). Measured on
``benchmarks.dense_light``'s 75 cases with the intrinsics given (box-solver starts, one run,
each case both ways in turn): 44 started so; the median fit took 46 ms against 62 (p95 72
against 91), within 5 %/2° 74 and within 2 %/1° 68 either way. ``python -m
benchmarks.dense_refine`` against every level for every start (12 pairs, one run): 43 against
55 ms. Through the stack (``cosmos bench --free --scene demo --random-scenes 2 --n 8``, seeds 1
and 3, one run each way): no outcome changed, within 2 %/1° 102 → 104 and 57 → 58 of 120. At
0.7 a generated scene's start that left 0.745 on its textured ground, 0.3 units off, stayed in
its fine-level basin, 3 % off where the coarse levels took it to 0.04 %."""
ZOOM_STARTS: Final = tuple(1.08**i for i in range(-2, 3))
"""Without given intrinsics, the first level starts from these zooms of the estimate's focal
length (each a dolly zoom that keeps the points' median depth in place): the distance-focal
valley is long and flat, and the box estimate's fov is off by ~7 % (median)."""
ZOOM_SIGMA: Final = 0.05
"""A fitted focal length is kept unless its standard deviation
(:func:`~.level_fit.parameter_sigma`, which counts the edge points as independent) passes this
share. Measured on free targets of
generated scenes without given intrinsics (seed 1, 96 targets): at the former 0.6 % the fits
of most 60–89° and nadir views were refused and the box estimate's focal (7–8 % off, median)
kept; fits of 1–4 % σ were mostly within 2 % of the true fov, and keeping every fit raised
the share within 5 % / 2° from 62 % to 76 %. Beyond 5 % (seen: 15 %) the fit has no hold."""
LIGHT_SHARE: Final = 0.6
"""The share of the render's off-outline edges (shadows, terminators) that must lie on the
target's edges at the outline's fit for them to join a last fit. Measured by ``python -m
benchmarks.dense_light`` (120 cases): at the outline's fit, the median share was 0.95 on clean
and JPEG images and 0.17 under another light; the last fit on both kept the ``photo`` cases
(39 of 40 within 5 %/2°) and brought JPEG back within 2 %/1° where the outline alone lost two."""


@dataclass(frozen=True)
class DenseFit:
    """A refined pose: world-to-camera ``rotation`` (3x3) and ``translation``, the
    ``intrinsics`` (scaled when the focal was fitted), the RMS edge distance of the explained
    points ``residual_px``, the model edge ``points`` used and how many are ``inliers`` (within
    :data:`INLIER_PX` of a target edge); ``start_inliers`` is that count at the start pose."""

    rotation: FloatArray
    translation: FloatArray
    intrinsics: Intrinsics
    residual_px: float
    points: int
    inliers: int
    start_inliers: int
    focal_fitted: bool = False
    """Whether the focal length was fitted: asked for, and pinned by the edges to within
    :data:`ZOOM_SIGMA` (else the start's is kept and only the pose refined)."""
    focal_sigma: float = math.nan
    """The fitted focal length's relative standard deviation
    (:func:`~.level_fit.parameter_sigma`; NaN when it
    was not fitted, ∞ when too few points were explained)."""
    depth: float = math.nan
    """The model points' median depth at the render's pose (scene units; NaN without points)."""
    chance: float = 0.0
    """The share of the points a pose placed at random would leave within :data:`INLIER_PX` of
    a target edge of their orientation (:func:`~.edges.edge_chance`): the target's edge
    density, above which the shares that decide are taken."""
    radial: RadialCheck | None = None
    """The lens check, when asked for (``check_radial``) and enough points were explained."""

    def share(self, count: int | None = None) -> float:
        """The share of the points that ``count`` (:attr:`inliers` by default) is above
        :attr:`chance` (:func:`~services.common.contracts.free.above_chance`)."""
        return above_chance(self.inliers if count is None else count, self.points, self.chance)

    @property
    def position(self) -> FloatArray:
        """The camera centre ``c = -Rᵀ t`` (scene units)."""
        centre: FloatArray = -self.rotation.T @ self.translation
        return centre

    def camera(self, start: PinholeCamera) -> PinholeCamera:
        """``start`` moved to this pose and intrinsics (same film)."""
        k = self.intrinsics
        return start.model_copy(
            update={
                "fov_deg": fov_deg_of(k.fx, start.width),
                "fx": k.fx,
                "fy": k.fy,
                "rotation": tuple(tuple(float(v) for v in row) for row in self.rotation),
                "translation": tuple(float(v) for v in self.translation),
                "position": tuple(float(v) for v in self.position),
            }
        )


def radial_only(distortion: LensDistortion | None) -> bool:
    """Whether ``distortion`` is none or OpenCV's radial ``k1`` alone: a lens the check can
    fit again (:func:`radial_check`)."""
    if distortion is None:
        return True
    return distortion.k2 == distortion.p1 == distortion.p2 == distortion.k3 == 0.0


def pyramid(pixel: float = 1.0) -> tuple[tuple[int, float, float], ...]:
    """:data:`LEVELS` on a film ``pixel`` ≥ 1 times the target's size (a small photo's grey
    enlarged): the coarse levels downsample as many target pixels as on the target's own film,
    and the finest is the film's own, its σ and τ the same number of target pixels, so that
    every tolerance keeps its meaning and only the edges' location gets finer."""
    coarse = tuple((max(1, round(f * pixel)), s, c) for f, s, c in LEVELS[:-1])
    _, sigma, cap = LEVELS[-1]
    return (*coarse, (1, sigma * pixel, cap * pixel))


def _zoomed(x: FloatArray, zoom: float, depth: float) -> FloatArray:
    """The pose-and-focal ``x`` zoomed by ``zoom`` and moved back along the optical axis by
    ``(zoom - 1) z``, so that points at depth ``z`` keep their pixels (a dolly zoom)."""
    y = x.copy()
    y[6] *= zoom
    y[5] += (zoom - 1.0) * depth
    return y


def _align(
    points: EdgePoints,
    levels: list[Level],
    k: Intrinsics,
    distortion: LensDistortion | None,
    x: FloatArray,
    zooms: Sequence[float] = ZOOM_STARTS,
) -> FloatArray:
    """Coarse to fine from ``x`` (pose, or pose and zoom when it has 7 entries, then started
    from each of its ``zooms``) over ``levels`` (the finest of :data:`LEVELS`, or all), keeping
    at each level the best by the full-resolution cost (module docstring)."""
    fit_focal = x.size == 7
    judge = ChamferProblem(points, levels[-1], k, distortion, fit_focal)

    def cost(y: FloatArray) -> float:
        return level_cost(judge.residuals(y), judge.level.sigma)

    candidates = [x]
    if fit_focal:
        rotation, _ = cv2.Rodrigues(x[:3])
        depth = float(np.median(points.world @ rotation[2] + x[5]))
        candidates = [_zoomed(x, zoom, depth) for zoom in zooms]
    costs = [cost(y) for y in candidates]
    for level, limit in zip(levels, LEVEL_POINTS[-len(levels) :], strict=True):
        problem = ChamferProblem(points, level, k, distortion, fit_focal, limit)
        # Each start keeps the better of its fit and itself by the full-resolution cost: a level
        # that slips into a wrong basin (repeated texture, say) never makes the pose worse.
        for i, y in enumerate(candidates):
            fitted = fit_level(problem, y)
            fitted_cost = cost(fitted)
            if fitted_cost < costs[i]:
                candidates[i], costs[i] = fitted, fitted_cost
    best = int(np.argmin(costs))
    return candidates[best] if costs[best] < cost(x) else x


def _with_the_light(
    x: FloatArray,
    points: EdgePoints,
    lit: EdgePoints,
    level: Level,
    k: Intrinsics,
    distortion: LensDistortion | None,
    focal_fitted: bool,
    radius: float = INLIER_PX,
) -> FloatArray:
    """``x`` (pose and zoom) refitted at ``level`` on the outline's ``points`` together with the
    render's edges off its outline (``lit``: its shadows and shading terminators) when at least
    :data:`LIGHT_SHARE` of those already lie on the target's edges at ``x``: the target then
    shares the render's light, and its shadows pin the pose too; else ``x``."""
    y = x if focal_fitted else x[:6]
    if len(lit.world) < MIN_POINTS:
        return x
    distances = ChamferProblem(lit, level, k, distortion, focal_fitted).residuals(y)
    if float(np.mean(distances <= radius)) < LIGHT_SHARE:
        return x
    both = EdgePoints(np.vstack([points.world, lit.world]), np.concatenate([points.bins, lit.bins]))
    fitted = fit_level(ChamferProblem(both, level, k, distortion, focal_fitted, MAX_POINTS), y)
    return fitted if focal_fitted else np.append(fitted, 1.0)


def refine_dense(
    target_gray: NDArray[np.uint8] | TargetMaps,
    render_rgb: NDArray[np.uint8],
    render_depth: NDArray[np.float32],
    camera: PinholeCamera,
    *,
    fit_focal: bool,
    distortion: LensDistortion | None = None,
    near: NDArray[np.bool_] | None = None,
    pixel: float = 1.0,
    focal_range: FocalRange | None = None,
    zooms: Sequence[float] = ZOOM_STARTS,
    check_radial: bool = False,
    radial_focal: bool | None = None,
) -> DenseFit:
    """Refine ``camera`` (the estimate the render was made at, on the target's film) so that the
    render's edges fall on the target's (module docstring).

    ``target_gray`` is the target ``(H, W)`` 8-bit grey (or RGB), or its maps kept between
    renders (:class:`~.target_maps.TargetMaps`), ``render_rgb`` ``(H, W, 3)``
    and ``render_depth`` ``(H, W)`` (``Z_c``, 0 where no surface) the render at ``camera``;
    ``fit_focal`` fits the focal length too (the target did not give its intrinsics);
    ``near`` ``(H, W)``, the pixels near the render's outline (:func:`~.edges.outline`), keeps
    only the edges no light moves, and the others join a last fit when the target shows them
    (:data:`LIGHT_SHARE`); ``pixel`` ≥ 1, the film's pixels per target pixel when a small
    target was enlarged to it: the levels are :func:`pyramid`'s, and a point is explained
    within :data:`INLIER_PX` of the target's pixels; ``focal_range``, the focal lengths considered
    on the film (:class:`~.focal_bounds.FocalRange`): a fitted one that ends outside it, or on
    a bound, is not kept; ``check_radial`` adds the lens check (:func:`radial_check`) when no
    ``distortion`` is given, or a radial ``k1`` alone (:func:`radial_only`, ``k1`` started
    there), the focal length free in it when ``radial_focal`` (by default when ``fit_focal``: a
    focal length stated but not trusted is freed there too). The answer's pixels are the
    film's.
    """
    target = target_gray if isinstance(target_gray, TargetMaps) else TargetMaps(target_gray)
    shape = (camera.height, camera.width)
    shapes = (render_rgb.shape[:2], render_depth.shape, shape if near is None else near.shape)
    if target.shape != shape or any(s != shape for s in shapes):
        raise ValueError(f"the target, render and depth must all be the camera's film {shape}")
    k = Intrinsics(camera.fx, camera.fy, camera.cx, camera.cy)
    rvec0, _ = cv2.Rodrigues(np.asarray(camera.rotation, dtype=np.float64))
    x0 = np.concatenate([rvec0.ravel(), np.asarray(camera.translation, dtype=np.float64), [1.0]])
    lit: EdgePoints | None = None  # the edges off the outline, for the last fit
    if near is None:
        points = edge_points(render_rgb, render_depth, camera, distortion)
    else:
        points, lit = edge_points_by_outline(render_rgb, render_depth, camera, distortion, near)
    levels_wanted = pyramid(pixel)
    radius = INLIER_PX * pixel
    fine = target.level(*levels_wanted[-1])
    chance = edge_chance(fine, points.bins, radius)
    pose_only = ChamferProblem(points, fine, k, distortion, fit_focal=False)
    start = pose_only.residuals(x0[:6])
    levels = [fine]
    start_share = above_chance(int((start <= radius).sum()), len(start), chance)
    if fit_focal or start_share < FINE_START_SHARE:
        levels = [
            fine if scale == 1 else target.level(scale, sigma, cap)
            for scale, sigma, cap in levels_wanted
        ]
    x, focal_fitted, focal_sigma = x0, False, math.nan
    rotation0 = np.asarray(camera.rotation, dtype=np.float64)
    depths = points.world @ rotation0[2] + x0[5]
    if len(points.world) >= MIN_POINTS:
        if fit_focal:
            x = _align(points, levels, k, distortion, x0, zooms)
            focal_sigma = parameter_sigma(
                ChamferProblem(points, fine, k, distortion, True), x, radius
            )
            beyond = focal_range is not None and at_bound(k.fx * x[6], focal_range)
            focal_fitted = focal_sigma <= ZOOM_SIGMA and not beyond
        if not focal_fitted:
            x = np.append(_align(points, levels, k, distortion, x0[:6]), 1.0)
        if lit is not None:
            x = _with_the_light(x, points, lit, fine, k, distortion, focal_fitted, radius)
    final = (
        pose_only.residuals(x[:6])
        if not focal_fitted
        else ChamferProblem(points, fine, k, distortion, True).residuals(x)
    )
    explained = final <= radius
    radial = None
    if check_radial and radial_only(distortion) and len(points.world) >= MIN_POINTS:
        free = fit_focal if radial_focal is None else radial_focal
        start_k1 = 0.0 if distortion is None else distortion.k1
        radial = radial_check(points, fine, k, x, pixel, free, start_k1)
    rotation, _ = cv2.Rodrigues(x[:3])
    zoom = float(x[6])
    return DenseFit(
        rotation=np.asarray(rotation, dtype=np.float64),
        translation=np.asarray(x[3:6], dtype=np.float64),
        intrinsics=Intrinsics(k.fx * zoom, k.fy * zoom, k.cx, k.cy),
        residual_px=float(np.sqrt(np.mean(final[explained] ** 2))) if explained.any() else math.inf,
        points=len(points.world),
        inliers=int(explained.sum()),
        start_inliers=int((start <= radius).sum()),
        focal_fitted=focal_fitted,
        focal_sigma=focal_sigma,
        depth=float(np.median(depths)) if depths.size else math.nan,
        chance=chance,
        radial=radial,
    )
