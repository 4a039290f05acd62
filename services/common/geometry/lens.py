"""Projection through a lens with OpenCV distortion, its inverse, and whether it folds the film.

The pinhole part is :class:`~services.common.geometry.camera.PinholeCamera`; the distortion is
:class:`~services.common.geometry.free_camera.LensDistortion` (``k1, k2, p1, p2, k3``, the model
of ``cv2.projectPoints``). Pixel (0, 0) is the top-left corner of the top-left pixel, as in
:func:`~services.common.geometry.camera.project`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.geometry.camera import PinholeCamera, project
from services.common.geometry.free_camera import LensDistortion

__all__ = [
    "UNDISTORT_TOLERANCE_PX",
    "distort",
    "fold_radius",
    "image_folds",
    "invertible_over_film",
    "project_lens",
    "undistort_pixels",
]

FloatArray = NDArray[np.float64]
UNDISTORT_TOLERANCE_PX = 1e-3
"""How far a pixel, undistorted and distorted again, may land from where it was."""


def _radial(d: LensDistortion, r2: FloatArray | float) -> FloatArray | float:
    """The radial factor ``1 + k1 r² + k2 r⁴ + k3 r⁶`` at ``r2`` = r²."""
    return 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))


def distort(xy: ArrayLike, distortion: LensDistortion) -> FloatArray:
    """Distort normalised coordinates ``(..., 2)`` (the equations of :class:`LensDistortion`)."""
    pts = np.asarray(xy, dtype=np.float64)
    x, y = pts[..., 0], pts[..., 1]
    d = distortion
    r2 = x * x + y * y
    radial = _radial(d, r2)
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return np.stack([xd, yd], axis=-1)


def project_lens(
    points: ArrayLike, camera: PinholeCamera, distortion: LensDistortion | None
) -> tuple[FloatArray, FloatArray]:
    """Project world points ``(..., 3)`` to distorted pixels ``(..., 2)``, and their depth.

    ``(u, v) = (fx x_d + cx, fy y_d + cy)`` with ``(x_d, y_d)`` the distorted
    ``(X_c / Z_c, Y_c / Z_c)``; without distortion this is
    :func:`~services.common.geometry.camera.project`. Points behind the camera get NaN.
    """
    pixels, depth = project(points, camera)
    if distortion is None or distortion.is_zero:
        return pixels, depth
    xy = np.stack(
        [(pixels[..., 0] - camera.cx) / camera.fx, (pixels[..., 1] - camera.cy) / camera.fy],
        axis=-1,
    )
    xy_d = distort(xy, distortion)
    out = np.stack([camera.fx * xy_d[..., 0] + camera.cx, camera.fy * xy_d[..., 1] + camera.cy], -1)
    return out, depth


def fold_radius(distortion: LensDistortion) -> float:
    """The undistorted radius r* where the radial model stops increasing (inf if it never does).

    ``r_d = r (1 + k1 r² + k2 r⁴ + k3 r⁶)`` has ``dr_d/dr = 1 + 3 k1 s + 5 k2 s² + 7 k3 s³`` in
    s = r², 1 at s = 0; r*² is its smallest positive real root (``numpy.roots``, then two Newton
    steps to polish the companion matrix's eigenvalue).
    """
    d = distortion
    slope = np.polynomial.Polynomial([1.0, 3.0 * d.k1, 5.0 * d.k2, 7.0 * d.k3])
    roots = np.roots(slope.coef[::-1])  # leading zeros (k3 = 0, …) are trimmed
    real = roots[np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots))].real
    positive = real[real > 0.0]
    if positive.size == 0:
        return math.inf
    s = float(np.min(positive))
    for _ in range(2):
        step = slope.deriv()(s)
        if step != 0.0:
            s -= slope(s) / step
    return math.sqrt(s)


def image_folds(camera: PinholeCamera, distortion: LensDistortion) -> bool:
    """Whether the radial distortion folds the film: some corner's distorted radius (normalised)
    lies at or beyond ``r_d(r*)``, the largest the monotonic part of the model reaches, so two
    directions would land on one pixel. The tangential terms are not part of this test; the
    round trip of :func:`undistort_pixels` catches what they break."""
    r_star = fold_radius(distortion)
    if math.isinf(r_star):
        return False
    reach = r_star * float(_radial(distortion, r_star**2))
    xs = (np.array([0.0, camera.width]) - camera.cx) / camera.fx
    ys = (np.array([0.0, camera.height]) - camera.cy) / camera.fy
    corner = math.sqrt(float(np.max(xs**2)) + float(np.max(ys**2)))
    return corner >= reach


def undistort_pixels(
    pixels: ArrayLike, camera: PinholeCamera, distortion: LensDistortion
) -> FloatArray:
    """The normalised undistorted coordinates ``(..., 2)`` of distorted pixels ``(..., 2)``.

    ``cv2.undistortPoints`` iterated to convergence (1e-12, at most 200 steps; its default is 5
    steps, far off at strongly distorted corners). Raises
    ``ValueError`` when a pixel, distorted again, lands more than :data:`UNDISTORT_TOLERANCE_PX`
    from where it was: the model has no unique inverse there.
    """
    px = np.asarray(pixels, dtype=np.float64)
    flat = px.reshape(-1, 1, 2)
    matrix = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    xy = cv2.undistortPoints(
        flat, matrix, distortion.coefficients(), R=None, P=None, criteria=criteria
    ).reshape(px.shape)
    back = distort(xy, distortion)
    again = np.stack(
        [camera.fx * back[..., 0] + camera.cx, camera.fy * back[..., 1] + camera.cy], -1
    )
    error = float(np.max(np.abs(again - px))) if px.size else 0.0
    if not error <= UNDISTORT_TOLERANCE_PX:
        raise ValueError(f"the distortion has no unique inverse over the film ({error:.3g} px off)")
    return np.asarray(xy, dtype=np.float64)


def invertible_over_film(
    camera: PinholeCamera, distortion: LensDistortion, samples: int = 64
) -> bool:
    """Whether ``distortion`` neither folds ``camera``'s film (:func:`image_folds`) nor lacks an
    inverse along its border (``samples`` points a side through :func:`undistort_pixels`): a lens
    a photo can have been taken through, and the renderer can draw."""
    if distortion.is_zero:
        return True
    if image_folds(camera, distortion):
        return False
    t = np.linspace(0.0, 1.0, samples)
    w, h = float(camera.width), float(camera.height)
    zero, one = np.zeros_like(t), np.ones_like(t)
    border = np.concatenate(
        [
            np.stack([t * w, zero], 1),
            np.stack([t * w, one * h], 1),
            np.stack([zero, t * h], 1),
            np.stack([one * w, t * h], 1),
        ]
    )
    try:
        undistort_pixels(border, camera, distortion)
    except ValueError:
        return False
    return True
