"""A camera's pose (and focal length) by least squares on box edges, and its centre-based start.

The pose is world-to-camera ``X_c = R(ω) X + t`` with ``ω`` a rotation vector (Rodrigues). For
paired detections ``i ↔ objects j(i)`` with observed boxes ``b_i`` and the projected boxes
``B_j(ω, t, f)`` of the objects' points (:func:`.objects.project_boxes`), the fit minimises

.. math:: \\sum_i \\sum_{s \\in S_i} ρ\\big((B_{j(i),s} - b_{i,s})^2\\big), \\qquad
          ρ(z) = 2(\\sqrt{1 + z/σ^2} - 1)\\,σ^2

(soft-L1 with scale σ = :data:`EDGE_SCALE_PX`), over ``(ω, t)`` or ``(ω, t, log f)``. ``S_i``
are the sides of box ``i`` that do not touch the image border: a clipped side says only that
the object goes on past the border, nothing about where it ends. The residual reported is the
RMS of the unrobustified edge differences over the unmasked sides, in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from services.common.geometry.camera import focal_length_px, fov_deg_of
from services.optimizer.free.focal_bounds import FocalRange, zoom_bounds
from services.optimizer.free.objects import NEAR_DEPTH, SceneObjects, project_boxes
from services.optimizer.geometry import FloatArray

__all__ = [
    "EDGE_SCALE_PX",
    "Intrinsics",
    "PoseFit",
    "centre_pnp",
    "pose_uncertainty",
    "refine_edges",
]

EDGE_SCALE_PX: Final = 1.0
"""Soft-L1 scale: edge differences beyond about a pixel count linearly, not squared."""
BIAS_ITERATIONS: Final = 3
MAX_EVALUATIONS: Final = 40
"""Residual evaluations per fit (besides the Jacobian's). Measured on rendered targets with the
focal length free: the fit has settled (same pose and fov to 1e-6) by 60, while the default
(100 per parameter) spent ten times as long creeping along the flat distance-focal valley. The
fits that reach the cap are of wrong hypotheses (soft-L1 cost 25-115, creeping): at 60 they were
a quarter of the fits and two thirds of the evaluations of a solve without intrinsics. At 30 or
40 every answer (status, pose to 1e-3 units and 0.05°, fov to 0.02°) was the one 60 gave on the
16 cameras of ``tests/optimizer/test_free_pose.py`` (own and general labels, intrinsics given or
not) and the free targets of ``python -m cosmos.bench.free_targets --scene demo
--random-scenes 2 --n 8 --seed 1``; at 20 one bench target's pose moved 66°. 40 keeps twice
the evaluations that failed."""
_FAR_PX: Final = 1e4
"""Residual that stands for an object behind the camera: large, finite, so the solver backs off."""


@dataclass(frozen=True)
class Intrinsics:
    """OpenCV pinhole intrinsics in pixels of the image the boxes refer to."""

    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def of_fov(cls, fov_deg: float, width: float, height: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view."""
        f = focal_length_px(fov_deg, width)
        return cls(fx=f, fy=f, cx=width / 2.0, cy=height / 2.0)

    def scaled(self, factor: float) -> Intrinsics:
        """The focal lengths times ``factor`` (a zoom), the principal point kept."""
        return replace(self, fx=self.fx * factor, fy=self.fy * factor)

    def on_film(self, factor: float) -> Intrinsics:
        """These intrinsics on the image scaled by ``factor`` (all four times it)."""
        return Intrinsics(self.fx * factor, self.fy * factor, self.cx * factor, self.cy * factor)

    def fov_deg(self, width: float) -> float:
        """The horizontal field of view over an image ``width`` pixels wide."""
        return fov_deg_of(self.fx, width)

    def matrix(self) -> FloatArray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class PoseFit:
    """A fitted pose: world-to-camera rotation vector and translation, the intrinsics used, the
    edge RMS over all pairs and per pair (pixels)."""

    rvec: FloatArray
    tvec: FloatArray
    intrinsics: Intrinsics
    rms_px: float
    pair_rms_px: FloatArray

    def rotation(self) -> FloatArray:
        """World-to-camera rotation matrix R."""
        r, _ = cv2.Rodrigues(self.rvec)
        return np.asarray(r, dtype=np.float64)

    def position(self) -> FloatArray:
        """Camera centre in world coordinates, ``c = -Rᵀ t``."""
        c: FloatArray = -self.rotation().T @ self.tvec
        return c


def _edge_errors(
    objects: SceneObjects,
    boxes: FloatArray,
    masks: NDArray[np.bool_],
    rvec: FloatArray,
    tvec: FloatArray,
    intrinsics: Intrinsics,
) -> FloatArray:
    """(n, 4) projected minus observed edges of paired ``objects`` (the subset in pair order),
    zero on masked sides, :data:`_FAR_PX` for an object behind the camera."""
    rotation, _ = cv2.Rodrigues(rvec)
    projected = project_boxes(
        objects, rotation, tvec, (intrinsics.fx, intrinsics.fy), (intrinsics.cx, intrinsics.cy)
    )
    diff = np.nan_to_num(projected - boxes, nan=_FAR_PX)
    diff[masks] = 0.0
    return diff


def _edge_jacobian(
    objects: SceneObjects,
    masks: NDArray[np.bool_],
    rvec: FloatArray,
    tvec: FloatArray,
    intrinsics: Intrinsics,
    fit_focal: bool,
) -> FloatArray:
    """(4n, 6 or 7) derivatives of the edges of :func:`_edge_errors` by ``(ω, t[, log f])``.

    A box edge is a coordinate of one extreme point (the argmin or argmax of its object's
    projected points), so its derivative is that point's projection's: ``cv2.projectPoints``
    gives it by ``ω``, ``t``, ``f_x`` and ``f_y``; by ``log f`` it is ``f_x ∂/∂f_x + f_y ∂/∂f_y``.
    One projection and one call, where finite differences cost a projection per parameter.
    """
    rotation, _ = cv2.Rodrigues(rvec)
    cam = objects.points @ rotation.T + tvec
    depth = cam[:, 2]
    uv = cam[:, :2] / np.maximum(depth, NEAR_DEPTH)[:, np.newaxis]
    owners = objects.owners()
    extremes = np.empty((len(objects), 4), dtype=np.intp)
    for side, (axis, reduce) in enumerate(
        ((0, np.minimum), (1, np.minimum), (0, np.maximum), (1, np.maximum))
    ):
        bound = reduce.reduceat(uv[:, axis], objects.starts)
        hit = np.flatnonzero(uv[:, axis] == bound[owners])
        _, first = np.unique(owners[hit], return_index=True)
        extremes[:, side] = hit[first]
    _, jac = cv2.projectPoints(
        objects.points[extremes.ravel()], rvec, tvec, intrinsics.matrix(), None
    )
    rows = 2 * np.arange(extremes.size) + np.tile([0, 1, 0, 1], len(objects))
    picked = np.asarray(jac, dtype=np.float64)[rows]
    out: FloatArray = picked[:, :6]
    if fit_focal:
        focal = intrinsics.fx * picked[:, 6] + intrinsics.fy * picked[:, 7]
        out = np.concatenate([out, focal[:, np.newaxis]], axis=1)
    behind = np.logical_or.reduceat(depth <= NEAR_DEPTH, objects.starts)
    out[(masks | behind[:, np.newaxis]).ravel()] = 0.0
    return out


def _rms(diff: FloatArray, masks: NDArray[np.bool_]) -> tuple[float, FloatArray]:
    used = (~masks).sum(axis=1)
    pair = np.sqrt((diff**2).sum(axis=1) / np.maximum(used, 1))
    total = math.sqrt(float((diff**2).sum()) / max(int(used.sum()), 1))
    return total, pair


def refine_edges(
    objects: SceneObjects,
    boxes: ArrayLike,
    masks: ArrayLike,
    rvec: ArrayLike,
    tvec: ArrayLike,
    intrinsics: Intrinsics,
    *,
    fit_focal: bool = False,
    focal_range: FocalRange | None = None,
) -> PoseFit:
    """Least squares on the box edges (module docstring).

    Parameters
    ----------
    objects : the paired objects, one per box, in the boxes' order (:meth:`SceneObjects.subset`).
    boxes : (n, 4) observed boxes, pixels.
    masks : (n, 4) sides to ignore (clipped by the image border).
    rvec, tvec : the start, world-to-camera.
    intrinsics : the camera's; with ``fit_focal`` its focal lengths are scaled by a fitted
        common factor (aspect ratio and principal point kept) that keeps ``fx`` within
        ``focal_range`` (:class:`~.focal_bounds.FocalRange`, pixels; by default
        :data:`~.focal_bounds.FOCAL_BOUNDS` of the start's ``fx``).
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    m = np.asarray(masks, dtype=np.bool_).reshape(-1, 4)
    start = np.concatenate([np.ravel(rvec), np.ravel(tvec)] + ([[0.0]] if fit_focal else []))

    def unpack(p: FloatArray) -> tuple[FloatArray, FloatArray, Intrinsics]:
        k = intrinsics.scaled(math.exp(p[6])) if fit_focal else intrinsics
        return p[:3], p[3:6], k

    def residuals(p: FloatArray) -> FloatArray:
        return _edge_errors(objects, b, m, *unpack(p)).ravel()

    def jacobian(p: FloatArray) -> FloatArray:
        return _edge_jacobian(objects, m, *unpack(p), fit_focal)

    bounds = (np.full(start.size, -np.inf), np.full(start.size, np.inf))
    if fit_focal:
        focal = FocalRange.about(intrinsics.fx) if focal_range is None else focal_range
        low, high = (math.log(z) for z in zoom_bounds(intrinsics.fx, focal))
        bounds[0][6], bounds[1][6] = low, high
    fit = least_squares(
        residuals,
        start,
        jac=jacobian,
        bounds=bounds,
        loss="soft_l1",
        f_scale=EDGE_SCALE_PX,
        x_scale="jac",
        method="trf",
        max_nfev=MAX_EVALUATIONS,
    )
    r, t, k = unpack(fit.x)
    total, pair = _rms(_edge_errors(objects, b, m, r, t, k), m)
    return PoseFit(rvec=r.copy(), tvec=t.copy(), intrinsics=k, rms_px=total, pair_rms_px=pair)


def centre_pnp(
    objects: SceneObjects,
    boxes: ArrayLike,
    masks: ArrayLike,
    rvec: ArrayLike,
    tvec: ArrayLike,
    intrinsics: Intrinsics,
    iterations: int = BIAS_ITERATIONS,
) -> tuple[FloatArray, FloatArray]:
    """PnP on box centres against the objects' centroids, corrected for the box-centre bias.

    A box's centre is not its object's projected centroid: perspective shifts a silhouette
    (a sphere's by ``≈ a (ρ/Z)²`` in normalised units, away from the principal point) and an
    object's outline is not symmetric about its centroid. With ``B_j``, ``p_j`` the projected box
    and centroid at the current pose, the observed centre is corrected to
    ``b̂_i = c(b_i) - (c(B_j) - p_j)`` and the pose re-solved (OpenCV's iterative PnP from the
    current pose), ``iterations`` times. Clipped boxes are left out while at least four
    unclipped ones remain: their centres are not their objects'. Not while three remain: three
    centres are fitted exactly, so a moved object's among them set the pose (a demo view went
    1.3 radii off from a start 2 % off). Replayed on seven free bench runs
    (``benchmarks.free_replay --dump``, 1,080 targets) against leaving them out from three:
    box estimates within 5 %/2° one more (that view), within 10 %/5° three more, none fewer.
    Cut boxes compared with their projected boxes cut alike instead: 3 more and 2 fewer within
    5 %/2°, an exact nadir fit of three cut boxes lost.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    m = np.asarray(masks, dtype=np.bool_).reshape(-1, 4)
    keep = ~m.any(axis=1)
    if keep.sum() < 4:
        keep = np.ones(len(b), dtype=np.bool_)
    r = np.asarray(rvec, dtype=np.float64).reshape(3).copy()
    t = np.asarray(tvec, dtype=np.float64).reshape(3).copy()
    if keep.sum() < 3:
        return r, t
    k = intrinsics.matrix()
    centres = (b[:, :2] + b[:, 2:]) / 2.0
    for _ in range(iterations):
        rotation, _ = cv2.Rodrigues(r)
        projected = project_boxes(objects, rotation, t, (k[0, 0], k[1, 1]), (k[0, 2], k[1, 2]))
        cam = objects.centroids @ rotation.T + t
        dot = cam[:, :2] / cam[:, 2:3] * (k[0, 0], k[1, 1]) + (k[0, 2], k[1, 2])
        bias = (projected[:, :2] + projected[:, 2:]) / 2.0 - dot
        target = centres - np.nan_to_num(bias)
        ok, r_new, t_new = cv2.solvePnP(
            objects.centroids[keep],
            target[keep],
            k,
            None,
            r.reshape(3, 1).copy(),
            t.reshape(3, 1).copy(),
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok or not np.all(np.isfinite(t_new)):
            break
        r = np.asarray(r_new, dtype=np.float64).reshape(3)
        t = np.asarray(t_new, dtype=np.float64).reshape(3)
    return r, t


def pose_uncertainty(
    objects: SceneObjects,
    boxes: ArrayLike,
    masks: ArrayLike,
    fit: PoseFit,
    sigma_px: float,
    *,
    with_focal: bool = False,
) -> tuple[float, float]:
    """1-σ position (scene units) and rotation (degrees) uncertainty of a fitted pose, from the
    Gauss–Newton covariance of the box edges with ``sigma_px`` of noise on each edge.

    With ``J`` the Jacobian of the edge residuals with respect to the camera centre ``c`` and a
    small world-frame turn ``δ`` of the camera (``R_cw ← exp([δ]×) R_cw``), both by central
    differences, ``Σ = σ² (JᵀJ)⁻¹``; the answers are ``√tr Σ_c`` and ``√tr Σ_δ`` in degrees. With
    ``with_focal`` (an estimated focal length) ``log f`` is a seventh parameter, so that the
    pose's uncertainty includes what the focal's leaves open (a dolly zoom: farther and
    narrower). A view that boxes barely pin (a nadir view of objects of one height trades tilt
    for shift) shows here as a large σ, though its residual is small.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    m = np.asarray(masks, dtype=np.bool_).reshape(-1, 4)
    rotation_cw = fit.rotation().T
    centre = fit.position()

    def residuals(p: FloatArray) -> FloatArray:
        turn, _ = cv2.Rodrigues(p[:3])
        r_wc = (np.asarray(turn) @ rotation_cw).T
        rvec, _ = cv2.Rodrigues(r_wc)
        tvec = -r_wc @ (centre + p[3:6])
        k = fit.intrinsics.scaled(math.exp(p[6])) if with_focal else fit.intrinsics
        r = np.asarray(rvec, dtype=np.float64).reshape(3)
        return _edge_errors(objects, b, m, r, tvec, k)[~m].ravel()

    steps = np.array(
        [1e-5] * 3 + [1e-5 * max(1.0, float(np.linalg.norm(centre)))] * 3 + [1e-5] * with_focal
    )
    columns = []
    for i, h in enumerate(steps):
        e = np.zeros(7)
        e[i] = h
        columns.append((residuals(e) - residuals(-e)) / (2.0 * h))
    jac = np.stack(columns, axis=1)
    normal = jac.T @ jac
    if jac.shape[0] < len(steps) or np.linalg.cond(normal) > 1e12:
        return math.inf, math.inf
    cov = sigma_px**2 * np.linalg.inv(normal)
    rotation_sigma = math.degrees(math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0)))
    return math.sqrt(max(float(np.trace(cov[3:, 3:])), 0.0)), rotation_sigma
