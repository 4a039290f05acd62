"""The longitude solve: the azimuth φ that rotates camera-relative offsets onto world positions.

Derivation (replaces the paper's garbled eq. 8)
------------------------------------------------
Eq. 7 maps an object's camera-relative ground offset ``q_i = (q_i1, q_i2)`` (towards the camera,
to the image's right; see :mod:`services.optimizer.geometry`) to its world ground position by the
2-D rotation ``p_i = R(φ) q_i``. Given matched pairs and weights ``w_i ≥ 0``, minimise

.. math:: E(φ) = \\sum_i w_i \\lVert \\mathbf{p}_i - R(φ)\\,\\mathbf{q}_i \\rVert^2
               = \\sum_i w_i (\\lVert \\mathbf{p}_i \\rVert^2 + \\lVert \\mathbf{q}_i \\rVert^2)
                 - 2 \\sum_i w_i\\, \\mathbf{p}_i^\\top R(φ)\\, \\mathbf{q}_i .

Writing ``R(φ) q = (q1 cos φ − q2 sin φ, q1 sin φ + q2 cos φ)``,

.. math:: \\sum_i w_i\\, \\mathbf{p}_i^\\top R(φ)\\, \\mathbf{q}_i = C \\cos φ + S \\sin φ, \\qquad
          C = \\sum_i w_i (\\mathbf{q}_i \\cdot \\mathbf{p}_i), \\quad
          S = \\sum_i w_i (\\mathbf{q}_i \\times \\mathbf{p}_i),

with the 2-D cross product ``q × p = q1 p2 − q2 p1``. ``C cos φ + S sin φ = √(C² + S²) cos(φ − ψ)``
with ``ψ = atan2(S, C)``, so the least-squares azimuth is the closed form

.. math:: \\hat φ = \\operatorname{atan2}(S, C)

(in complex numbers: ``φ̂ = arg Σ w_i p_i conj(q_i)``), and the minimum is
``E(φ̂) = Σ w_i (|p_i|² + |q_i|²) − 2√(C² + S²)``. No translation is fitted: both frames are
centred on the scene centre, which every hemisphere camera looks at.

The solve is undetermined when ``C = S = 0`` (all offsets at the centre, or no pairs). Its
*coherence* ``κ = √(C² + S²) / Σ w_i |p_i| |q_i| ∈ [0, 1]`` is 1 when every pair agrees on the
same angle and falls as they disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["RotationFit", "solve_rotation"]


@dataclass(frozen=True)
class RotationFit:
    """The least-squares rotation between matched 2-D point sets.

    Attributes
    ----------
    phi_deg : float
        The azimuth φ̂ in [0, 360) degrees; NaN when undetermined.
    rms : float
        Root weighted mean squared residual ``√(E(φ̂) / Σ w)``, in the points' units.
    coherence : float
        ``κ`` in [0, 1] (0 when undetermined).
    """

    phi_deg: float
    rms: float
    coherence: float

    @property
    def determined(self) -> bool:
        """Whether the pairs fix an angle at all."""
        return math.isfinite(self.phi_deg)


def _unit_scaled(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``values`` divided by their largest magnitude (unchanged when all are 0 or none)."""
    largest = float(np.max(np.abs(values))) if values.size else 0.0
    out: NDArray[np.float64] = values / largest if largest > 0.0 else values
    return out


def solve_rotation(
    offsets: ArrayLike, positions: ArrayLike, weights: ArrayLike | None = None
) -> RotationFit:
    """The azimuth φ minimising ``Σ w_i |p_i − R(φ) q_i|²`` in closed form (module docstring).

    Parameters
    ----------
    offsets : array_like, shape (n, 2)
        Camera-relative offsets ``q_i``.
    positions : array_like, shape (n, 2)
        World positions ``p_i``, same units.
    weights : array_like, shape (n,), optional
        Non-negative weights (default 1). Pairs with non-finite values are left out.

    Returns
    -------
    RotationFit
    """
    q = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if q.shape != p.shape:
        raise ValueError(f"offsets {q.shape} and positions {p.shape} must match")
    w = np.ones(len(q)) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (len(q),):
        raise ValueError(f"weights must have shape ({len(q)},), got {w.shape}")
    if np.any(w < 0.0):
        raise ValueError("weights must be non-negative")
    keep = np.isfinite(q).all(axis=1) & np.isfinite(p).all(axis=1) & np.isfinite(w) & (w > 0)
    q, p, w = q[keep], p[keep], w[keep]
    # c, s and their scale each scale by max|q| max|p| max w, which leaves φ and the coherence
    # alone: on the sets scaled to at most 1, points of 1e-155 do not underflow to subnormals
    # (they made the coherence test depend on the weights' scale).
    qn, pn, wn = (_unit_scaled(a) for a in (q, p, w))
    c = float(np.sum(wn * (qn[:, 0] * pn[:, 0] + qn[:, 1] * pn[:, 1])))
    s = float(np.sum(wn * (qn[:, 0] * pn[:, 1] - qn[:, 1] * pn[:, 0])))
    magnitude = math.hypot(c, s)
    total = float(np.sum(w))
    scale = float(np.sum(wn * np.linalg.norm(qn, axis=1) * np.linalg.norm(pn, axis=1)))
    if total <= 0.0 or magnitude <= 1e-12 * max(scale, 1e-300):
        spread = float(np.sum(w * (np.sum(q**2, axis=1) + np.sum(p**2, axis=1))))
        rms = math.sqrt(spread / total) if total > 0 else math.nan
        return RotationFit(phi_deg=math.nan, rms=rms, coherence=0.0)
    angle = math.atan2(s, c)
    phi = math.degrees(angle) % 360.0
    # The residual evaluated directly: the expanded form cancels badly when it is small.
    cos_a, sin_a = math.cos(angle), math.sin(angle)
    rotated = np.stack([cos_a * q[:, 0] - sin_a * q[:, 1], sin_a * q[:, 0] + cos_a * q[:, 1]], -1)
    energy = float(np.sum(w * np.sum((p - rotated) ** 2, axis=1)))
    return RotationFit(
        phi_deg=0.0 if phi >= 360.0 else phi,
        rms=math.sqrt(energy / total),
        coherence=min(1.0, magnitude / scale) if scale > 0 else 0.0,
    )
