"""Object mapping (paper §3.2): ground positions of detected objects seen from a known pose.

Two methods turn a detection box (camera pixels, see
:meth:`.observations.Observation.from_detections`) into the footprint centre ``p`` of the object
on the ground plane and its camera-relative offset ``q = R(φ)ᵀ p``
(:mod:`services.optimizer.geometry`).

``paper`` — eq. 2–7
-------------------
The camera at polar angle θ on a hemisphere of radius r is tilted ``θ_x = 90° − θ`` below the
horizontal, looking at the scene centre, whose ground distance from the camera's foot is
``r sin θ``. The ray through the box centre's row ``v_b`` (camera pixels ``s · v``, ``s`` the
scale of :class:`~.calibration.PaperCalibration`) dips

.. math:: α = \\arctan\\frac{s\\,v_b - v_c}{f} \\quad (2), \\qquad β = θ_x + α \\quad (3)

below the horizontal. It meets the horizontal plane the box centres lie in — the camera height
above it is ``y_c = r cos θ − h`` — at ``y_c / tan β`` from the camera's foot, so the depth
offset of the object beyond the scene centre is

.. math:: Δx = \\frac{y_c}{\\tan β} − r \\sin θ \\quad (4)

(``r sin θ`` is the paper's ``y_c / tan θ_x`` written so the pole needs no limit; undefined
where the ray never reaches the plane, ``y_c sin β ≤ 0``). The paper's balls share one centre
height; for any scene ``h`` is fitted with the lateral coefficients
(:func:`.calibration.fit_reference_height`), and ``h = 0`` is eq. 4 read literally (rays meet
the ground itself), which puts every raised object too far away by ``h_c / tan β`` — 0.7 scene
units (median) for the demo balls. The lateral offset ``Δy`` is eq. 5–6 with coefficients fitted
on rendered views (:mod:`.calibration`), and eq. 7 rotates ``q = (−Δx, Δy)`` by φ. Objects of
other heights than ``h`` keep a bias ``(h_c − h) / tan β``, largest for low cameras.

``exact`` — back-projection through the pinhole camera (ours)
--------------------------------------------------------------
Each class has a proxy solid (:mod:`.proxies`) with footprint centre ``(x, y)``, footprint
half-width ρ and height H, all unknown; the box gives four equations (its edges), so position and
size are solved *jointly* from the box alone, with no size prior:

*Sphere* (closed form, exact). The left and right box edges are the image lines whose planes
through the camera centre touch the ball (:func:`.proxies._tangent_bounds`): with normalised
edge coordinates ``a₁ < a₂`` and ``s_k = √(1 + a_k²)`` the centre ``C`` satisfies
``C_x − a₁ C_z = ρ s₁`` and ``a₂ C_z − C_x = ρ s₂``. Hence

.. math:: \\frac{C_x}{C_z} = \\frac{a_1 s_2 + a_2 s_1}{s_1 + s_2}, \\qquad
          k = \\frac{ρ}{C_z} = \\frac{a_2 − a_1}{s_1 + s_2},

and likewise from the top and bottom edges (``b_k``, ``t_k = √(1 + b_k²)``). The box centre is
*not* the projection of the ball's centre: ``(a₁ + a₂)/2 = a_c / (1 − k²)``, an outward shift
``≈ a_c k²`` (about 0.5 px at the image edge for the demo balls), which the weighted mean above
removes. With the ray ``w = Rᵀ (a_c, b_c, 1)`` the centre is ``c + C_z w``, and the ball resting
on the ground puts it at height ρ = k C_z: ``c_z + C_z w_z = k C_z`` gives
``C_z = c_z / (k − w_z)``. Reference point: the ball's centre, at height ρ.

*Upright solids* (cube, cylinder, cone, mesh → prism or cone proxy). The bottom edge of the box
is the image of the footprint's front point, which lies *on the ground*: the ray through the
bottom edge's midpoint meets z = 0 at ``g``, the footprint half-width follows from the box width
at that depth, ``ρ ≈ (a₂ − a₁) Z_g / 2``, and the footprint centre lies ρ beyond ``g`` along the
horizontal viewing direction. The top edge fixes H (far rim of a prism's top face, a cone's
apex). This closed form starts a damped Gauss–Newton solve of all four box edges for
``(x, y, log ρ, log H)`` through the proxy's forward model, which removes the small errors of
the closed form (the rim's extreme point is not exactly below the box's midpoint). Reference
point: the footprint's front point on the ground — the only point of an unknown solid whose
height is known. The box centre at an assumed height would need the object's height, which a
box alone gives only through this same joint solve.

A mesh is only a prism to the optimizer: an elongated footprint seen broadside is pushed back by
half its length instead of half its depth, which is why meshes map an order of magnitude worse
than primitives (``benchmarks/mapping.py``). A box overlapped by one reaching lower in the image
belongs to an object probably partly hidden behind a nearer one; it is mapped but flagged
unreliable (:func:`hidden_behind`).

Both solves use only box edges that are not cut by the image border. A 1-pixel error in the
edges maps to a positional uncertainty ``σ`` from the Gauss–Newton normal matrix; it grows
without bound as the camera nears the horizon, and such objects are marked unreliable. A camera
*on* the horizon (θ = 90°) sits in the ground plane: scaling the whole scene about the camera
centre keeps every object on the ground and leaves the image unchanged, so no view from there
fixes a distance, and nothing is mapped from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import PaperCalibration
from services.optimizer.geometry import (
    FloatArray,
    PinholeCameras,
    ground_offsets,
    world_from_offsets,
)
from services.optimizer.proxies import ProxyKind, proxy_boxes

__all__ = [
    "EDGE_MARGIN_PX",
    "MappedObjects",
    "clipped_sides",
    "hidden_behind",
    "map_exact",
    "map_paper",
    "paper_offsets",
]

EDGE_MARGIN_PX: Final = 0.5
"""A box side within this of the image border is taken as cut by it (camera pixels)."""

_HORIZON: Final = 1e-6  # camera height per unit radius below which nothing can be mapped
_RELIABLE_SIGMA: Final = 0.03  # positional σ per unit hemisphere radius for a reliable mapping
_LM_ITERATIONS: Final = 12
_PIXEL_SIGMA: Final = 1.0


@dataclass(frozen=True)
class MappedObjects:
    """Objects of one view mapped to the ground; row ``i`` belongs to detection ``i``.

    Attributes
    ----------
    position : ndarray, shape (n, 2)
        World footprint centres, scene units (NaN when the method fails).
    offsets : ndarray, shape (n, 2)
        Camera-relative offsets ``q = R(φ)ᵀ p``.
    radius, height : ndarray, shape (n,)
        Footprint half-width ρ and height H (NaN for the paper method).
    sigma : ndarray, shape (n,)
        Positional standard deviation for 1-pixel edge errors, scene units (NaN: unknown).
    reliable : ndarray of bool, shape (n,)
        Finite, not cut at the bottom by the image border, not overlapped by a nearer box
        (:func:`hidden_behind`), and ``σ`` small.
    """

    position: FloatArray
    offsets: FloatArray
    radius: FloatArray
    height: FloatArray
    sigma: FloatArray
    reliable: NDArray[np.bool_]


def clipped_sides(boxes: ArrayLike, width: float, height: float) -> NDArray[np.bool_]:
    """``(n, 4)`` flags: which sides ``[x1, y1, x2, y2]`` touch the image border."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return np.stack(
        [
            b[:, 0] <= EDGE_MARGIN_PX,
            b[:, 1] <= EDGE_MARGIN_PX,
            b[:, 2] >= width - EDGE_MARGIN_PX,
            b[:, 3] >= height - EDGE_MARGIN_PX,
        ],
        axis=1,
    )


def hidden_behind(boxes: ArrayLike) -> NDArray[np.bool_]:
    """``(n,)`` flags: boxes that overlap another box whose bottom edge is lower in the image.

    Objects stand on the ground and the camera looks down on them, so of two overlapping boxes
    the one reaching lower is nearer: the other is probably partly hidden, its box shrunk, and
    its mapping biased.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    wide = np.minimum(b[:, None, 2], b[None, :, 2]) - np.maximum(b[:, None, 0], b[None, :, 0])
    tall = np.minimum(b[:, None, 3], b[None, :, 3]) - np.maximum(b[:, None, 1], b[None, :, 1])
    overlap = (wide > 0.0) & (tall > 0.0)
    np.fill_diagonal(overlap, False)
    lower = b[None, :, 3] > b[:, None, 3]
    hidden: NDArray[np.bool_] = np.any(overlap & lower, axis=1)
    return hidden


# -- exact -------------------------------------------------------------------------------------


def _sphere_guess(cam: PinholeCameras, boxes: FloatArray, valid: NDArray[np.bool_]) -> FloatArray:
    """Closed-form ``(x, y, ρ)`` of balls from their boxes (module docstring)."""
    a1, b1 = cam.normalised(boxes[:, 0:2]).T
    a2, b2 = cam.normalised(boxes[:, 2:4]).T
    s1, s2, t1, t2 = (np.sqrt(1.0 + z**2) for z in (a1, a2, b1, b2))
    both_h = valid[:, 0] & valid[:, 2]
    both_v = valid[:, 1] & valid[:, 3]
    k_h = np.where(both_h, (a2 - a1) / (s1 + s2), np.nan)
    k_v = np.where(both_v, (b2 - b1) / (t1 + t2), np.nan)
    both = np.stack([k_h, k_v])
    count = np.sum(np.isfinite(both), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(count > 0, np.nansum(both, axis=0) / count, np.nan)

    def centre(
        lo: FloatArray, hi: FloatArray, slo: FloatArray, shi: FloatArray, i: int
    ) -> FloatArray:
        return np.where(
            valid[:, i] & valid[:, i + 2],
            (lo * shi + hi * slo) / (slo + shi),
            np.where(valid[:, i], lo + slo * k, hi - shi * k),
        )

    a_c = centre(a1, a2, s1, s2, 0)
    b_c = centre(b1, b2, t1, t2, 1)
    w = cam.directions(np.stack([a_c, b_c], axis=-1))[0]
    c = cam.position[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = c[2] / (k - w[:, 2])
    centre_xyz = c + depth[:, np.newaxis] * w
    rho = k * depth
    bad = ~(np.isfinite(depth) & (depth > 0.0) & (rho > 0.0))
    out = np.stack([centre_xyz[:, 0], centre_xyz[:, 1], rho], axis=-1)
    out[bad] = np.nan
    return out


def _solid_guess(
    cam: PinholeCameras, boxes: FloatArray, kinds: NDArray[np.int_], valid: NDArray[np.bool_]
) -> FloatArray:
    """Closed-form ``(x, y, ρ, H)`` of upright solids from their boxes (module docstring)."""
    u_mid = (boxes[:, 0] + boxes[:, 2]) / 2.0
    # A box cut at the bottom has no ground point: fall back to its centre row (a poor guess
    # that the joint solve then improves as far as the remaining edges allow).
    v_low = np.where(valid[:, 3], boxes[:, 3], (boxes[:, 1] + boxes[:, 3]) / 2.0)
    c = cam.position[0]
    low = cam.directions(cam.normalised(np.stack([u_mid, v_low], axis=-1)))[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = np.where(low[:, 2] < 0.0, -c[2] / low[:, 2], np.nan)
    ground = c + lam[:, np.newaxis] * low
    horizontal = ground[:, :2] - c[:2]
    distance = np.linalg.norm(horizontal, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        toward = horizontal / distance[:, np.newaxis]
    width_n = (boxes[:, 2] - boxes[:, 0]) / cam.focal_px
    rho = width_n * lam / 2.0
    foot = ground[:, :2] + rho[:, np.newaxis] * toward
    top = cam.directions(cam.normalised(np.stack([u_mid, boxes[:, 1]], axis=-1)))[0]
    reach = np.linalg.norm(foot - c[:2], axis=1) + np.where(kinds == ProxyKind.CONE, 0.0, rho)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = c[2] + reach / np.linalg.norm(top[:, :2], axis=1) * top[:, 2]
    height = np.maximum(height, 0.1 * rho)
    return np.stack([foot[:, 0], foot[:, 1], rho, height], axis=-1)


def _edges(
    cam: PinholeCameras, kinds: NDArray[np.int_], spheres: NDArray[np.bool_], params: FloatArray
) -> FloatArray:
    """Forward model: boxes ``(m, 4)`` of proxies with ``params = (x, y, log ρ, log H)``
    (``spheres`` flags the balls, whose height is their diameter)."""
    physical = np.empty_like(params)
    physical[:, :2] = params[:, :2]
    physical[:, 2] = np.exp(params[:, 2])
    physical[:, 3] = np.where(spheres, 2.0 * physical[:, 2], np.exp(params[:, 3]))
    boxes: FloatArray = proxy_boxes(cam, kinds, physical)[0]
    return boxes


def _refine(
    cam: PinholeCameras,
    kinds: NDArray[np.int_],
    boxes: FloatArray,
    valid: NDArray[np.bool_],
    start: FloatArray,
    radius: float,
) -> tuple[FloatArray, FloatArray]:
    """Damped Gauss–Newton (Levenberg–Marquardt) fit of the valid box edges, vectorised over
    objects; returns parameters ``(n, 4)`` and the positional σ ``(n,)`` for 1-pixel edges."""
    n = len(kinds)
    params = start.copy()
    mask = valid.astype(np.float64)
    spheres = kinds == ProxyKind.SPHERE.value
    free = np.ones((n, 4))
    free[spheres, 3] = 0.0  # a ball's height is its diameter
    steps = np.array([1e-6 * radius, 1e-6 * radius, 1e-6, 1e-6])
    damping = np.full(n, 1e-3)
    # Sizes stay between a millionth and twice the hemisphere radius: keeps exp() finite.
    log_lo, log_hi = math.log(1e-6 * radius), math.log(2.0 * radius)

    shifts = np.zeros((5, 1, 4))
    shifts[np.arange(1, 5), 0, np.arange(4)] = steps
    kinds5, spheres5 = np.tile(kinds, 5), np.tile(spheres, 5)
    boxes5, mask5 = np.tile(boxes, (5, 1)), np.tile(mask, (5, 1))

    def evaluate(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Residuals ``(n, edge)`` at ``p`` and their forward-difference Jacobian
        ``(n, edge, param)`` from one batch of proxies (a proxy's box does not depend on the
        rest of the batch), so an accepted trial step brings its Jacobian along."""
        r = (_edges(cam, kinds5, spheres5, (p + shifts).reshape(-1, 4)) - boxes5) * mask5
        r = np.where(np.isfinite(r), r, 1e6).reshape(5, n, 4)
        jac = (r[1:] - r[0]) / steps[:, np.newaxis, np.newaxis]  # (param, n, edge)
        return r[0], np.transpose(jac, (1, 2, 0)) * free[:, np.newaxis, :]

    r0, jac = evaluate(params)
    cost = (r0**2).sum(axis=1)
    eye = np.eye(4)
    tiny, pinned = 1e-9 * eye, eye * (1.0 - free[:, :, np.newaxis])
    for _ in range(_LM_ITERATIONS):
        normal = np.einsum("nei,nej->nij", jac, jac)
        gradient = np.einsum("nei,ne->ni", jac, r0)
        diag = np.einsum("nii->ni", normal)
        system = normal + (damping[:, None, None] * (diag[:, :, None] * eye + tiny))
        system += pinned
        delta = -np.linalg.solve(system, gradient[..., np.newaxis])[..., 0] * free
        if float(np.abs(delta).max(initial=0.0)) < 1e-10:
            break  # converged everywhere
        trial = params + delta
        trial[:, 2:] = np.minimum(np.maximum(trial[:, 2:], log_lo), log_hi)
        r_trial, jac_trial = evaluate(trial)
        cost_trial = (r_trial**2).sum(axis=1)
        better = cost_trial < cost
        np.copyto(params, trial, where=better[:, np.newaxis])
        np.copyto(r0, r_trial, where=better[:, np.newaxis])
        np.copyto(jac, jac_trial, where=better[:, np.newaxis, np.newaxis])
        np.copyto(cost, cost_trial, where=better)
        damping *= np.where(better, 0.3, 10.0)
    normal = np.einsum("nei,nej->nij", jac, jac) + pinned
    # A tiny ridge instead of a pseudo-inverse: a direction the edges do not constrain (the
    # scale of everything seen from the horizon) must come out with a huge variance, not zero.
    ridge = 1e-12 * np.maximum(np.einsum("nii->n", normal), 1e-300)
    covariance = np.linalg.inv(normal + ridge[:, None, None] * eye) * _PIXEL_SIGMA**2
    sigma = np.sqrt(np.maximum(covariance[:, 0, 0] + covariance[:, 1, 1], 0.0))
    return params, sigma


def map_exact(
    boxes: ArrayLike, kinds: ArrayLike, camera: CameraSpec, theta_deg: float, phi_deg: float
) -> MappedObjects:
    """Exact back-projection of boxes seen from pose (θ, φ) (module docstring).

    Parameters
    ----------
    boxes : array_like, shape (n, 4)
        ``[x1, y1, x2, y2]`` in the camera's pixels (pixel edges).
    kinds : array_like of int, shape (n,)
        :class:`~.proxies.ProxyKind` per box.
    camera : CameraSpec
        Field of view, film size and hemisphere radius.
    theta_deg, phi_deg : float
        The pose the boxes were seen from.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    kind = np.asarray(kinds, dtype=np.int_).reshape(-1)
    n = len(b)
    cam = PinholeCameras.at(theta_deg, phi_deg, camera)
    cut = clipped_sides(b, camera.width, camera.height)
    if cam.position[0, 2] <= _HORIZON * camera.radius:
        nan = np.full(n, np.nan)
        return MappedObjects(
            np.full((n, 2), np.nan), np.full((n, 2), np.nan), nan, nan, nan, np.zeros(n, bool)
        )
    valid = ~cut
    start = np.full((n, 4), np.nan)
    spheres = kind == ProxyKind.SPHERE
    if spheres.any():
        guess = _sphere_guess(cam, b[spheres], valid[spheres])
        start[spheres] = np.stack(
            [guess[:, 0], guess[:, 1], guess[:, 2], 2.0 * guess[:, 2]], axis=-1
        )
    if (~spheres).any():
        start[~spheres] = _solid_guess(cam, b[~spheres], kind[~spheres], valid[~spheres])
    finite = np.isfinite(start).all(axis=1) & (start[:, 2] > 0.0) & (start[:, 3] > 0.0)
    physical = np.full((n, 4), np.nan)
    sigma = np.full(n, np.nan)
    if finite.any():
        logs = start[finite].copy()
        logs[:, 2:] = np.clip(
            np.log(logs[:, 2:]), math.log(1e-6 * camera.radius), math.log(2.0 * camera.radius)
        )
        fitted, sig = _refine(cam, kind[finite], b[finite], valid[finite], logs, camera.radius)
        rho = np.exp(fitted[:, 2])
        height = np.where(kind[finite] == ProxyKind.SPHERE, 2.0 * rho, np.exp(fitted[:, 3]))
        physical[finite] = np.stack([fitted[:, 0], fitted[:, 1], rho, height], axis=-1)
        sigma[finite] = sig
    position = physical[:, :2]
    reliable = (
        np.isfinite(position).all(axis=1)
        & ~cut[:, 3]
        & ~hidden_behind(b)
        & (sigma <= _RELIABLE_SIGMA * camera.radius)
    )
    return MappedObjects(
        position=position,
        offsets=ground_offsets(position, phi_deg),
        radius=physical[:, 2],
        height=physical[:, 3],
        sigma=sigma,
        reliable=reliable,
    )


# -- paper -------------------------------------------------------------------------------------


def paper_offsets(
    boxes: ArrayLike, camera: CameraSpec, theta_deg: ArrayLike, calibration: PaperCalibration
) -> FloatArray:
    """Camera-relative offsets ``q = (−Δx, Δy)`` ``(T, n, 2)`` of box centres by eq. 2–6, for
    every candidate polar angle in ``theta_deg`` ``(T,)`` (the camera height y_c = r cos θ and
    tilt θ_x = 90° − θ follow from θ). NaN where the ray misses the ground (β ≤ 0).
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    theta = np.radians(np.atleast_1d(np.asarray(theta_deg, dtype=np.float64)))[:, np.newaxis]
    s = calibration.scale(camera)
    f = calibration.width / 2.0 / math.tan(math.radians(calibration.fov_deg) / 2.0)
    u_c, v_c = calibration.width / 2.0, calibration.height / 2.0
    u = s * (b[:, 0] + b[:, 2]) / 2.0
    v = s * (b[:, 1] + b[:, 3]) / 2.0
    y_c = camera.radius * np.cos(theta) - calibration.reference_height
    tilt = math.pi / 2.0 - theta
    alpha = np.arctan((v - v_c) / f)  # eq. 2
    beta = tilt + alpha  # eq. 3
    with np.errstate(divide="ignore", invalid="ignore"):
        # eq. 4, with y_c / tan θ_x written as r sin θ so the pole (θ_x = 90°) needs no limit;
        # the ray meets the plane only where it heads towards it (sin β and y_c of one sign).
        meets = np.sin(beta) * y_c > 0.0
        dx = np.where(meets, y_c / np.tan(beta), np.nan) - camera.radius * np.sin(theta)
    coef = calibration.lateral_coefficients(np.degrees(theta[:, 0]))[:, np.newaxis, :]
    dy = (coef[..., 0] * v + coef[..., 1]) * (u - u_c) + (coef[..., 2] * v + coef[..., 3])
    return np.stack([-dx, np.broadcast_to(dy, dx.shape)], axis=-1)


def map_paper(
    boxes: ArrayLike,
    camera: CameraSpec,
    theta_deg: float,
    phi_deg: float,
    calibration: PaperCalibration,
) -> MappedObjects:
    """The paper's mapping (eq. 2–7) of boxes seen from pose (θ, φ)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    offsets = paper_offsets(b, camera, [theta_deg], calibration)[0]
    position = world_from_offsets(offsets, phi_deg)
    cut = clipped_sides(b, camera.width, camera.height)
    n = len(b)
    return MappedObjects(
        position=position,
        offsets=offsets,
        radius=np.full(n, np.nan),
        height=np.full(n, np.nan),
        sigma=np.full(n, np.nan),
        reliable=np.asarray(np.isfinite(position).all(axis=1) & ~cut.any(axis=1), dtype=bool),
    )
