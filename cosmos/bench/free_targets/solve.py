"""The two references a free search is measured against, on the same targets.

:func:`baseline_pnp`
    What a user would write first: OpenCV's ``cv2.solvePnPRansac`` with its default flags
    (``SOLVEPNP_ITERATIVE``, 100 iterations, 8 px reprojection threshold) on the boxes' centres
    against the objects' 3D centroids, paired by object name, with the intrinsics known. A box's
    centre is not its centroid's projection (perspective moves it), which this baseline ignores.
:func:`box_fit`, :func:`box_only_bound`
    The ideal box-only fit: each object's exact projected bounding box
    (:func:`~cosmos.bench.free_targets.shapes.project_boxes`) with Gaussian noise of σ per edge
    (0.7 px at 320x240, the detector's measured box error, scaled with the film's width), fitted
    by least squares on the four edges of every box over the 6-DoF pose, starting from the truth.
    Starting from the truth takes the search for a start out: it is the best any method that
    only sees boxes can reach. The intrinsics are known when the target gives them; when it does
    not, the focal length is fitted too (from the truth's), as any method must: the bound then
    says what the boxes alone tell of the focal length, which a dolly zoom trades against
    distance.

The fit minimises, over the rotation vector ω (world to camera, R = exp([ω]ₓ)), the camera
centre c (scene units) and, without the intrinsics, the log of a zoom s of the focal lengths,

    Σᵢ Σₑ (b̂ᵢₑ(ω, c, s) − bᵢₑ)²,

b̂ᵢ = [min u, min v, max u, max v] over object i's hull points X projected as K_s (R X − R c)
(K_s: K with f_x, f_y times s), clipped to the film (a clipped edge carries no information and
has no gradient), bᵢ the observed box.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cosmos.bench.free_targets.draw import FreeTarget
from cosmos.bench.free_targets.estimate import Estimate, fov_of_focal, intrinsics_matrix
from cosmos.bench.free_targets.shapes import SceneShapes, project_boxes

__all__ = [
    "BOX_SIGMA_PX",
    "BOX_SIGMA_WIDTH",
    "baseline",
    "baseline_pnp",
    "box_fit",
    "box_only_bound",
    "box_sigma_px",
]

FloatArray = NDArray[np.float64]
BOX_SIGMA_PX: Final = 0.7
BOX_SIGMA_WIDTH: Final = 320
""":data:`BOX_SIGMA_PX` is the edge noise on a film this many pixels wide."""


def box_sigma_px(width: int) -> float:
    """The box-edge noise on a ``width``-pixel film: 0.7 px at 320 pixels, in proportion."""
    return BOX_SIGMA_PX * width / BOX_SIGMA_WIDTH


def baseline_pnp(
    centroids: FloatArray, box_centres: FloatArray, intrinsics: FloatArray, fov_deg: float
) -> Estimate | None:
    """``cv2.solvePnPRansac`` with its defaults on paired centroids ``(N, 3)`` and box centres
    ``(N, 2)`` (pixels); None when OpenCV refuses (too few points) or finds no pose. A pose it
    reports found but with NaN in it (degenerate pairs: every box centre on one pixel, say) is
    no pose either: one such garden target (seed 31) stopped a whole ``cosmos bench --free``
    run."""
    try:
        ok, rvec, tvec, _inliers = cv2.solvePnPRansac(
            np.ascontiguousarray(centroids, dtype=np.float64),
            np.ascontiguousarray(box_centres, dtype=np.float64),
            intrinsics,
            None,
        )
    except cv2.error:
        return None
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    rotation = np.asarray(cv2.Rodrigues(rvec)[0], dtype=np.float64)
    return Estimate.of_world_to_camera(
        rotation, np.asarray(tvec, dtype=np.float64).ravel(), fov_deg
    )


def baseline(target: FreeTarget) -> Estimate | None:
    """:func:`baseline_pnp` on the target's exact boxes of its usable objects (a detector's
    boxes stand in for them once the bench detects), with the true intrinsics."""
    ann = target.annotations
    objects = [obj for obj in ann.objects if obj.name in target.usable and obj.box is not None]
    centroids = np.array([obj.centroid for obj in objects], dtype=np.float64)
    boxes = np.array([obj.box for obj in objects], dtype=np.float64)
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2.0
    return baseline_pnp(centroids, centres, intrinsics_matrix(ann.camera), ann.camera.fov_deg)


def _pose_vector(estimate: Estimate) -> FloatArray:
    rotation, _ = estimate.world_to_camera
    return np.concatenate([Rotation.from_matrix(rotation).as_rotvec(), estimate.position])


def _zoomed(intrinsics: FloatArray, log_zoom: float) -> FloatArray:
    """``K`` with its focal lengths times ``exp(log_zoom)``, the principal point kept."""
    k = np.array(intrinsics, dtype=np.float64)
    k[0, 0] *= math.exp(log_zoom)
    k[1, 1] *= math.exp(log_zoom)
    return k


def _boxes_at(
    x: FloatArray, shapes: SceneShapes, intrinsics: FloatArray, film: tuple[int, int]
) -> FloatArray:
    """The boxes at pose ``x`` (ω, c and, when it has seven entries, the log zoom)."""
    rotation = Rotation.from_rotvec(x[:3]).as_matrix()
    k = _zoomed(intrinsics, float(x[6])) if x.size == 7 else intrinsics
    return project_boxes(shapes, rotation, -rotation @ x[3:6], k, film)


def box_fit(
    shapes: SceneShapes,
    boxes: FloatArray,
    intrinsics: FloatArray,
    film: tuple[int, int],
    start: Estimate,
    *,
    fit_focal: bool = False,
) -> Estimate:
    """The least-squares pose on the box edges (module docstring) of ``shapes``' objects, whose
    observed boxes are ``boxes`` ``(N, 4)``, from ``start`` with the focal lengths of
    ``intrinsics``; with ``fit_focal`` the focal length is fitted too, else the fov stays
    ``start``'s."""
    observed = np.asarray(boxes, dtype=np.float64).ravel()

    def residuals(x: FloatArray) -> FloatArray:
        return _boxes_at(x, shapes, intrinsics, film).ravel() - observed

    x0 = _pose_vector(start)
    if fit_focal:
        x0 = np.append(x0, 0.0)
    fit = least_squares(residuals, x0, x_scale="jac", xtol=1e-12, ftol=1e-12)
    rotation = Rotation.from_rotvec(fit.x[:3]).as_matrix()
    fov = start.fov_deg
    if fit_focal:
        fov = fov_of_focal(intrinsics[0, 0] * math.exp(float(fit.x[6])), film[0])
    return Estimate(rotation.T, np.asarray(fit.x[3:6], dtype=np.float64), fov)


def box_only_bound(
    target: FreeTarget,
    shapes: SceneShapes,
    rng: np.random.Generator,
    sigma_px: float | None = None,
    names: Sequence[str] | None = None,
) -> Estimate:
    """The ideal box-only fit of ``target`` (module docstring): the exact boxes of its usable
    objects (or ``names``) plus N(0, σ²) per edge (σ = :func:`box_sigma_px` unless given),
    fitted from the truth, the focal length too when the target does not give it."""
    camera = target.annotations.camera
    film = (camera.width, camera.height)
    used = shapes.subset(tuple(names) if names is not None else target.usable)
    truth = Estimate.of_camera(target.camera, camera.fov_deg, camera.width)
    rotation, translation = truth.world_to_camera
    intrinsics = intrinsics_matrix(camera)
    exact = project_boxes(used, rotation, translation, intrinsics)
    sigma = box_sigma_px(camera.width) if sigma_px is None else sigma_px
    noisy = exact + rng.normal(0.0, sigma, size=exact.shape) if sigma > 0 else exact
    limits = np.array([film[0], film[1], film[0], film[1]], dtype=np.float64)
    observed = np.clip(noisy, 0.0, limits)
    return box_fit(used, observed, intrinsics, film, truth, fit_focal=not target.intrinsics_given)
