"""Scoring poses by reprojecting the world map, and the continuous least-squares refinement.

Predicted boxes
---------------
Every map entry's proxy is projected into every grid pose (:meth:`.world_map.WorldMap.boxes`).
A proxy is only an approximation of its object (a mesh is not a cylinder), so the prediction is
*anchored* to what was actually seen: at a visited pose ``v`` the detection box ``B_vk`` of entry
``k`` differs from its prediction ``P̂_vk`` by an offset ``o_vk = B_vk − P̂_vk``, and near ``v``
the prediction becomes ``P̂_gk + w(d) o_vk`` with ``v`` the visited pose nearest to ``g`` (angle
``d`` between view directions) and ``w`` = 1 within two grid steps, fading linearly to 0 at
four. At a visited pose the prediction is then the observation itself, and next to it only the
map's predicted *change* matters, which is far more accurate than its absolute boxes.

Score of a pose
---------------
Entries whose box is at least 30 % inside the image and 2 px a side are *expected*. A target
detection ``j`` and an entry ``k`` with a box in the image may pair when they look alike
(appearance cost — colour, and class as :func:`~.observations.appearance_cost` has it — below
the colour gate); their cost is

.. math:: c_{jk} = t_k \\Bigl(\\frac{\\operatorname{rms}(B_j − \\hat B_k)}{s}\\Bigr)^2
                   + \\text{appearance cost}_{jk},

``rms`` the root mean square of the four box-edge differences in pixels, ``s`` =
:data:`SCALE_PX` and ``t_k`` the entry's trust (:attr:`.world_map.WorldMap.trust`: low for
objects only ever seen partly hidden or from the horizon, whose mapped positions are biased).
With the gate ``τ²`` (:data:`GATE`) the pose's score is the gated Hungarian optimum

.. math:: S = \\sum_{\\text{pairs}} \\min(c_{jk}, τ^2) + τ^2 \\, (\\#\\text{unpaired targets})
              + λ τ^2 \\, (\\#\\text{unpaired expected entries}),

λ = :data:`MISSING_WEIGHT` < 1 because an expected object may be hidden or missed in the target.
Every grid pose gets a cheap score first (each detection's best partner, not one-to-one); the
:data:`EXACT_CANDIDATES` best and up to :data:`FAR_CANDIDATES` distant local optima are then
scored exactly.

Refinement
----------
At the best pose the pairs are fixed and ``(θ, φ)`` minimise the soft-L1 robust sum of squared
box-edge residuals (pixels, anchored predictions) with :func:`scipy.optimize.least_squares`; the
RMS of the final residuals is the estimate's reprojection residual. The Jacobian is the solver's
own forward differences, predicted in one batch with the residuals (:func:`refine_pose`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec
from services.common.geometry.sphere import pose_to_cartesian
from services.optimizer.geometry import FloatArray, PinholeCameras
from services.optimizer.matching import COLOUR_GATE, Assignment, assign
from services.optimizer.observations import Observation, appearance_cost
from services.optimizer.proxies import clip_boxes
from services.optimizer.world_map import WorldMap

__all__ = [
    "EXACT_CANDIDATES",
    "FAR_CANDIDATES",
    "GATE",
    "MISSING_WEIGHT",
    "SCALE_PX",
    "Anchor",
    "Anchoring",
    "PoseScores",
    "Prediction",
    "Refinement",
    "anchor",
    "predict",
    "refine_pose",
    "score_poses",
]

SCALE_PX: Final = 4.0
GATE: Final = 16.0
MISSING_WEIGHT: Final = 0.5
EXACT_CANDIDATES: Final = 8
FAR_CANDIDATES: Final = 4
_FAR_SCAN: Final = 400
_MIN_INSIDE: Final = 0.3
_MIN_SIDE_PX: Final = 2.0
_ANCHOR_FULL_STEPS: Final = 2.0
_ANCHOR_FADE_STEPS: Final = 4.0
_DIFF_STEP: Final = 1e-4  # relative forward-difference step of the refinement
_SQRT_EPS: Final = float(np.sqrt(np.finfo(np.float64).eps))


@dataclass(frozen=True, eq=False)
class Anchor:
    """A visited pose (angles, degrees) with its detections and the entry each joined."""

    theta_deg: float
    phi_deg: float
    observation: Observation
    link: NDArray[np.intp]


@dataclass(frozen=True, eq=False)
class Prediction:
    """Predicted boxes ``(N, K, 4)`` (clipped) and the expected mask ``(N, K)``."""

    boxes: FloatArray
    expected: NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Anchoring:
    """Offsets ``(V, K, 4)`` observed-minus-predicted at each anchor (0 where the entry was not
    seen there) and the anchors' unit view directions ``(V, 3)``."""

    offsets: FloatArray
    directions: FloatArray

    @classmethod
    def of(cls, anchors: Sequence[Anchor], predicted: FloatArray) -> Anchoring:
        """The anchoring to the views ``anchors`` of a map whose (unanchored) boxes there are
        ``predicted`` ``(V, K, 4)`` (:meth:`.WorldMap.boxes`)."""
        offsets = np.zeros(predicted.shape)
        for v, anchor in enumerate(anchors):
            seen = anchor.link >= 0
            entries = anchor.link[seen]
            delta = anchor.observation.boxes[seen] - predicted[v, entries]
            offsets[v, entries] = np.nan_to_num(delta, nan=0.0)
        directions = pose_to_cartesian(
            [a.theta_deg for a in anchors], [a.phi_deg for a in anchors]
        ).reshape(-1, 3)
        return cls(offsets=offsets, directions=directions)

    def subset(self, entries: NDArray[np.intp]) -> Anchoring:
        """The anchoring of the map entries ``entries`` only (see :meth:`.WorldMap.subset`)."""
        return Anchoring(offsets=self.offsets[:, entries], directions=self.directions)


def _weights(step_deg: float, angle_deg: FloatArray) -> FloatArray:
    full, fade = _ANCHOR_FULL_STEPS * step_deg, _ANCHOR_FADE_STEPS * step_deg
    return np.minimum(np.maximum((fade - angle_deg) / (fade - full), 0.0), 1.0)


def anchor(
    boxes: FloatArray, cameras: PinholeCameras, anchoring: Anchoring, step_deg: float
) -> FloatArray:
    """Predicted boxes ``(N, K, 4)`` (clipped) of a map in ``cameras``, anchored (module
    docstring) from its unanchored ones ``boxes`` (:meth:`.WorldMap.boxes`). Each entry's boxes
    depend on that entry alone."""
    if not (len(anchoring.directions) and boxes.shape[1]):
        return boxes
    poses = cameras.unit_positions
    # minimum(maximum()) is np.clip without its Python wrapper (refine_pose calls this often).
    cosines = np.minimum(np.maximum(poses @ anchoring.directions.T, -1.0), 1.0)
    # Ties go to the latest visit: it was fused last and reflects the newest map.
    last = len(anchoring.directions) - 1
    nearest = last - np.argmax(cosines[:, ::-1], axis=1)
    angle = np.degrees(np.arccos(cosines[np.arange(len(poses)), nearest]))
    weight = _weights(step_deg, angle)[:, np.newaxis, np.newaxis]
    shift = anchoring.offsets[nearest] * weight
    anchored, _ = clip_boxes(boxes + shift, cameras.width, cameras.height)
    return anchored


def predict(
    boxes: FloatArray,
    inside: FloatArray,
    cameras: PinholeCameras,
    anchoring: Anchoring,
    step_deg: float,
) -> Prediction:
    """Anchored predicted boxes of a map in ``cameras`` and which entries each pose is expected
    to see (module docstring), from its unanchored boxes ``(N, K, 4)`` and the fraction
    ``(N, K)`` of each inside the image (:meth:`.WorldMap.boxes`)."""
    anchored = anchor(boxes, cameras, anchoring, step_deg)
    # A NaN side (no box) compares False, as a side of 0 would.
    expected = (
        (inside >= _MIN_INSIDE)
        & (anchored[..., 2] - anchored[..., 0] >= _MIN_SIDE_PX)
        & (anchored[..., 3] - anchored[..., 1] >= _MIN_SIDE_PX)
    )
    return Prediction(boxes=anchored, expected=expected)


@dataclass(frozen=True)
class PoseScores:
    """Scores of candidate poses (lower is better).

    Attributes
    ----------
    coarse : ndarray, shape (G,)
        Cheap score of every pose.
    candidates : ndarray of intp, shape (C,)
        Poses scored exactly, best first.
    exact : ndarray, shape (C,)
        Their exact scores.
    pairs : list of Assignment
        Target-to-map pairs at each candidate (rows: target detections, cols: map entries).
    """

    coarse: FloatArray
    candidates: NDArray[np.intp]
    exact: FloatArray
    pairs: list[Assignment]


def _pair_costs(world: WorldMap, target: Observation, prediction: Prediction) -> FloatArray:
    """Pair costs ``(n, K, N)`` (poses last: the long axis runs fastest); inf where a pair is
    not allowed."""
    predicted = np.ascontiguousarray(prediction.boxes.T)[:, np.newaxis]  # (edge, 1, K, N)
    diff = target.boxes.T[:, :, np.newaxis, np.newaxis] - predicted
    squared = np.sum(diff * diff, axis=0) / (4.0 * SCALE_PX**2)
    mismatch = max(target.mismatch_cost, world.mismatch_cost)
    looks = appearance_cost(target.labels, target.colors, world.labels, world.colors, mismatch)
    cost = squared * world.trust[:, np.newaxis] + looks[:, :, np.newaxis]
    # Any entry with a box in the image may pair, even one mostly outside it (a target can see
    # a sliver of an object); only the penalty for missing entries is limited to expected ones.
    ok = (looks < COLOUR_GATE)[:, :, np.newaxis] & np.isfinite(cost)
    return np.where(ok, cost, np.inf)


def _candidates(
    coarse: FloatArray, directions: FloatArray | None, near: int, far: int, separation_deg: float
) -> NDArray[np.intp]:
    """The ``near`` best poses by coarse score, plus up to ``far`` more that are each the best
    of their own neighbourhood (farther than ``separation_deg`` from every pose taken so far):
    distant look-alikes must be scored exactly to be found."""
    order = np.argsort(coarse, kind="stable")
    chosen = list(order[:near])
    if directions is None or far <= 0:
        return np.asarray(chosen, dtype=np.intp)
    limit = np.cos(np.radians(separation_deg))
    seeds = [directions[chosen[0]]] if chosen else []
    for pose in order[near : near + _FAR_SCAN]:
        if len(chosen) >= near + far:
            break
        if all(float(directions[pose] @ seed) < limit for seed in seeds):
            chosen.append(pose)
            seeds.append(directions[pose])
    return np.asarray(chosen, dtype=np.intp)


def score_poses(
    world: WorldMap,
    target: Observation,
    prediction: Prediction,
    candidates: int = EXACT_CANDIDATES,
    directions: FloatArray | None = None,
    separation_deg: float = 0.0,
) -> PoseScores:
    """Score every pose of ``prediction`` against the target's detections (module docstring).

    With the poses' unit view ``directions`` ``(N, 3)``, the exact scoring also covers up to
    :data:`FAR_CANDIDATES` distant local optima more than ``separation_deg`` apart."""
    cost = _pair_costs(world, target, prediction)
    expected = prediction.expected
    n = len(target)
    # Minima capped at the gate: min(c, τ²) over a set is its minimum capped.
    coarse = cost.min(axis=1, initial=GATE).sum(axis=0)
    map_side = cost.min(axis=0, initial=GATE).T
    coarse = coarse + MISSING_WEIGHT * GATE * np.sum(expected & (map_side >= GATE), axis=1)
    order = _candidates(coarse, directions, max(1, candidates), FAR_CANDIDATES, separation_deg)
    exact = np.empty(len(order))
    pairs: list[Assignment] = []
    expected_count = expected.sum(axis=1)
    for i, pose in enumerate(order):
        assignment = assign(cost[:, :, pose], GATE)
        unpaired_map = int(expected_count[pose]) - int(expected[pose, assignment.cols].sum())
        exact[i] = (
            float(assignment.costs.sum())
            + GATE * (n - len(assignment))
            + MISSING_WEIGHT * GATE * max(unpaired_map, 0)
        )
        pairs.append(assignment)
    ranked = np.argsort(exact, kind="stable")
    return PoseScores(
        coarse=coarse,
        candidates=order[ranked].astype(np.intp),
        exact=exact[ranked],
        pairs=[pairs[i] for i in ranked],
    )


@dataclass(frozen=True)
class Refinement:
    """A continuous pose fitted by least-squares reprojection (angles in degrees, residual in
    pixels over ``matched`` pairs). ``fit_deg`` is the robust fit's own ``(θ, φ)``: the pose
    unless its RMS came out above the start's, which is then kept. ``sigma_deg`` is the pose's
    1-σ angle on the sphere (:func:`_sigma_deg`)."""

    theta_deg: float
    phi_deg: float
    residual_px: float
    matched: int
    fit_deg: tuple[float, float] | None = None
    sigma_deg: float | None = None

    @property
    def kept_start(self) -> bool:
        """Whether the start was kept over the robust fit (see ``fit_deg``)."""
        return self.fit_deg is not None and self.fit_deg != (self.theta_deg, self.phi_deg)


def _forward_steps(x: FloatArray, lower: FloatArray, upper: FloatArray) -> FloatArray:
    """Forward-difference steps ``(2,)`` (degrees) at pose ``x`` = (θ, φ): those of
    :func:`scipy.optimize.least_squares` with ``diff_step`` = :data:`_DIFF_STEP`, i.e. that
    relative step of each coordinate (``√ε max(1, |x|)`` where it rounds to nothing), turned
    backwards where it would leave the bounds (which lie farther apart than any step)."""
    sign = np.where(x >= 0.0, 1.0, -1.0)
    step = _DIFF_STEP * sign * np.abs(x)
    step = np.where((x + step) - x == 0.0, _SQRT_EPS * sign * np.maximum(1.0, np.abs(x)), step)
    ahead = x + step
    return np.where((ahead < lower) | (ahead > upper), -step, step)


def refine_pose(
    world: WorldMap,
    target: Observation,
    pairs: Assignment,
    theta_deg: float,
    phi_deg: float,
    camera: CameraSpec,
    anchoring: Anchoring,
    grid: HemisphereGrid,
    theta_bounds: tuple[float, float] = (0.0, 90.0),
) -> Refinement:
    """Least-squares ``(θ, φ)`` from a starting pose with fixed pairs (module docstring).

    The residuals at a pose are predicted together with those at its two forward-difference
    poses, in one batch of three cameras: the solver asks for the Jacobian at every pose it
    accepts, and a batch costs about what a single pose does."""
    if len(pairs) == 0:
        return Refinement(theta_deg, phi_deg % 360.0, math.inf, 0)
    observed = target.boxes[pairs.rows]
    lower, upper = np.array([theta_bounds[0], -np.inf]), np.array([theta_bounds[1], np.inf])
    step = grid.angle_step_deg
    # Only the paired entries' boxes enter the residuals: predict those alone.
    paired, paired_anchoring = world.subset(pairs.cols), anchoring.subset(pairs.cols)

    def residuals(poses: FloatArray) -> FloatArray:
        """Residuals ``(P, 4 × pairs)`` in pixels at poses ``(P, 2)`` (degrees)."""
        cams = PinholeCameras.at(poses[:, 0], poses[:, 1], camera)
        predicted = anchor(paired.boxes(cams)[0], cams, paired_anchoring, step)
        r = (predicted - observed).reshape(len(poses), -1)
        return np.where(np.isfinite(r), r, 50.0)

    # The solver asks for poses it has evaluated again: remember them, not recompute.
    evaluated: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def linearise(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Residuals and their forward-difference Jacobian ``(4 × pairs, 2)`` (pixels per
        degree) at ``x``."""
        key = x.tobytes()
        if key not in evaluated:
            h = _forward_steps(x, lower, upper)
            r = residuals(np.vstack([x, x + np.diag(h)]))
            evaluated[key] = r[0], ((r[1:] - r[0]) / ((x + h) - x)[:, np.newaxis]).T
        return evaluated[key]

    start = np.array([min(max(theta_deg, lower[0] + 1e-9), upper[0] - 1e-9), phi_deg])
    # Copies: the solver scales its residuals and Jacobian in place.
    result = least_squares(
        lambda x: linearise(x)[0].copy(),
        start,
        jac=lambda x: linearise(x)[1].copy(),
        bounds=(lower, upper),
        loss="soft_l1",
        f_scale=3.0,
        max_nfev=60,
    )
    rms = float(np.sqrt(np.mean(linearise(result.x)[0] ** 2)))
    start_rms = float(np.sqrt(np.mean(linearise(start)[0] ** 2)))
    fit = (float(result.x[0]), float(result.x[1]) % 360.0)
    if rms > start_rms:
        sigma = _sigma_deg(*linearise(start), float(start[0]))
        return Refinement(float(start[0]), phi_deg % 360.0, start_rms, len(pairs), fit, sigma)
    return Refinement(*fit, rms, len(pairs), fit, _sigma_deg(*linearise(result.x), fit[0]))


def _sigma_deg(residuals: FloatArray, jacobian: FloatArray, theta_deg: float) -> float:
    """The 1-σ angle (degrees) of the view direction fitted at residuals ``r`` with Jacobian ``J``
    (pixels per degree of θ and φ): ``Σ = s² (JᵀJ)⁻¹`` with ``s² = Σr² / (n − 2)``, and the
    angle ``√(Σ_θθ + sin²θ Σ_φφ)`` (a step of φ turns the direction by ``sin θ`` of it)."""
    n = len(residuals)
    if n <= 2:
        return math.inf
    normal = jacobian.T @ jacobian
    if np.linalg.cond(normal) > 1e12:
        return math.inf
    cov = float(residuals @ residuals) / (n - 2) * np.linalg.inv(normal)
    sin = math.sin(math.radians(theta_deg))
    return math.sqrt(max(float(cov[0, 0]) + sin * sin * float(cov[1, 1]), 0.0))
