"""A world map of the objects, fused from every visited view, and its projection into any pose.

Each visited view's detections are mapped to proxies with the exact method (:mod:`.mapping`),
once per view content (:mod:`.view_cache`: a search sends its earlier views with every request).
Views are folded in one at a time: a mapped object joins the map entry it matches (alike class
and colour as :func:`~.observations.appearance_cost` has it, footprints closer than the gate)
by a gated Hungarian assignment, else it starts a new entry. An entry's parameters
``(x, y, ρ, H)`` are the inverse-variance weighted mean of its observations (weights ``1/σ²``
from the mapping's positional σ, floored at 1 % of the hemisphere radius so one lucky view
cannot dominate); its proxy kind is that of the detection that started it. Unreliable mappings
(near-horizon views, boxes cut at the bottom) only start entries when nothing reliable saw the
object, with a large σ, and mappings whose σ exceeds the hemisphere radius (views from the
horizon) are left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.geometry.scene import CameraSpec
from services.optimizer.geometry import FloatArray, PinholeCameras
from services.optimizer.matching import COLOUR_GATE, assign
from services.optimizer.observations import CLASS_MISMATCH_COST, Observation, appearance_cost
from services.optimizer.proxies import clip_boxes, proxy_boxes
from services.optimizer.view_cache import SHARED_MAPPINGS, ViewMappings

__all__ = ["MappedView", "WorldMap", "build_map"]

Links = list[NDArray[np.intp]]
"""Per view, the map entry each detection joined (-1: none)."""

_SIGMA_FLOOR: Final = 0.01  # per unit hemisphere radius
_UNRELIABLE_SIGMA: Final = 0.1  # per unit radius, for entries only unreliable views saw
_GATE_SIZES: Final = 1.5  # footprints closer than this many (ρ_a + ρ_b) may be one object
_TRUST_SIGMAS: Final = 3.0
_MIN_TRUST: Final = 0.1


@dataclass(frozen=True)
class MappedView:
    """A visited view: its pose and detections (camera pixels)."""

    theta_deg: float
    phi_deg: float
    observation: Observation


@dataclass(frozen=True, eq=False)
class WorldMap:
    """Fused objects.

    Attributes
    ----------
    labels : tuple of str
        Class per entry.
    kinds : ndarray of int, shape (K,)
        :class:`~.proxies.ProxyKind` per entry (that of the detection that started it).
    colors : ndarray, shape (K, 3)
        Mean sRGB colour, NaN when never measured.
    params : ndarray, shape (K, 4)
        Proxy ``(x, y, ρ, H)`` in scene units.
    sigma : ndarray, shape (K,)
        Positional standard deviation of the fused footprint centre.
    support : ndarray of int, shape (K,)
        Views that saw the entry (compared and hashed by identity: it holds arrays).
    sigma_floor : float
        The smallest σ an observation is given (1 % of the hemisphere radius).
    mismatch_cost : float
        Cost of pairing different labels (:func:`~.observations.appearance_cost`).
    """

    labels: tuple[str, ...]
    kinds: NDArray[np.int_]
    colors: FloatArray
    params: FloatArray
    sigma: FloatArray
    support: NDArray[np.int_]
    sigma_floor: float = 0.0
    mismatch_cost: float = CLASS_MISMATCH_COST

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def trust(self) -> FloatArray:
        """``(K,)`` weight of each entry's geometry when scoring poses, in [0.1, 1]: 1 for an
        entry any reliable view saw (σ within a few times the floor), down to 0.1 for one only
        unreliable views saw."""
        scale = _TRUST_SIGMAS * self.sigma_floor
        with np.errstate(divide="ignore"):
            weight = np.clip((scale / self.sigma) ** 2, _MIN_TRUST, 1.0)
        return np.nan_to_num(weight, nan=_MIN_TRUST)

    def subset(self, entries: NDArray[np.intp]) -> WorldMap:
        """The map of the entries ``entries`` alone, in that order."""
        return WorldMap(
            labels=tuple(self.labels[int(i)] for i in entries),
            kinds=self.kinds[entries],
            colors=self.colors[entries],
            params=self.params[entries],
            sigma=self.sigma[entries],
            support=self.support[entries],
            sigma_floor=self.sigma_floor,
            mismatch_cost=self.mismatch_cost,
        )

    def boxes(self, cameras: PinholeCameras) -> tuple[FloatArray, FloatArray]:
        """Predicted boxes ``(N, K, 4)`` clipped to the image, and the fraction of each
        unclipped box inside it ``(N, K)``, in every camera."""
        full = proxy_boxes(cameras, self.kinds, self.params)
        return clip_boxes(full, cameras.width, cameras.height)


@dataclass
class _Entry:
    label: str
    kind: int
    colours: list[FloatArray]
    params: list[FloatArray]
    weights: list[float]

    def fused(self) -> tuple[FloatArray, FloatArray, float]:
        w = np.array(self.weights)
        total = w.sum()
        params = (np.array(self.params) * w[:, np.newaxis]).sum(axis=0) / total
        colours = np.array(self.colours)
        known = ~np.isnan(colours).any(axis=1)
        count = np.count_nonzero(known)
        colour = colours[known].sum(axis=0) / count if count else np.full(3, np.nan)
        return params, colour, float(1.0 / np.sqrt(total))


def build_map(
    views: Sequence[MappedView], camera: CameraSpec, mappings: ViewMappings | None = None
) -> tuple[WorldMap, Links]:
    """Fuse the exact mappings of ``views`` into one map (module docstring).

    Views are mapped through ``mappings`` (default: the process's shared cache). Returns the
    map and, per view, the entry each detection joined (-1 when it joined none).
    """
    cache = SHARED_MAPPINGS if mappings is None else mappings
    entries: list[_Entry] = []
    links: Links = []
    floor = _SIGMA_FLOOR * camera.radius
    mismatch = max((v.observation.mismatch_cost for v in views), default=CLASS_MISMATCH_COST)
    for view in views:
        obs = view.observation
        link = np.full(len(obs), -1, dtype=np.intp)
        links.append(link)
        if len(obs) == 0:
            continue
        kinds = obs.kinds
        mapped = cache.get(obs, view.theta_deg, view.phi_deg, camera)
        params = np.column_stack([mapped.position, mapped.radius, mapped.height])
        # A σ beyond the hemisphere radius carries no information (horizon views).
        usable = np.isfinite(params).all(axis=1) & (mapped.sigma <= camera.radius)
        sigma = np.where(
            mapped.reliable, np.maximum(mapped.sigma, floor), _UNRELIABLE_SIGMA * camera.radius
        )
        current = [e.fused() for e in entries]
        if current:
            labels = [e.label for e in entries]
            colours = np.array([c for _, c, _ in current])
            fused = np.array([p for p, _, _ in current])
            looks = appearance_cost(obs.labels, obs.colors, labels, colours, mismatch)
            apart = np.linalg.norm(params[:, np.newaxis, :2] - fused[np.newaxis, :, :2], axis=-1)
            sizes = params[:, np.newaxis, 2] + fused[np.newaxis, :, 2]
            gate_distance = _GATE_SIZES * sizes
            cost = apart / gate_distance + looks / COLOUR_GATE
            allowed = (looks < COLOUR_GATE) & (apart < gate_distance) & usable[:, np.newaxis]
            pairs = assign(np.where(allowed, cost, np.inf), 2.0)
            joined = dict(zip(pairs.rows.tolist(), pairs.cols.tolist(), strict=True))
        else:
            joined = {}
        for i in range(len(obs)):
            if not usable[i]:
                continue
            weight = 1.0 / sigma[i] ** 2
            if i in joined:
                entry = entries[joined[i]]
                link[i] = joined[i]
                if not mapped.reliable[i] and max(entry.weights) > weight:
                    continue  # an unreliable look adds nothing to a reliable entry
                entry.params.append(params[i])
                entry.colours.append(obs.colors[i])
                entry.weights.append(weight)
            else:
                link[i] = len(entries)
                entry = _Entry(obs.labels[i], int(kinds[i]), [obs.colors[i]], [params[i]], [weight])
                entries.append(entry)
    if not entries:
        empty = WorldMap(
            (),
            np.zeros(0, dtype=np.int_),
            np.zeros((0, 3)),
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros(0, int),
            floor,
            mismatch,
        )
        return empty, links
    fused_all = [e.fused() for e in entries]
    world = WorldMap(
        labels=tuple(e.label for e in entries),
        kinds=np.array([e.kind for e in entries], dtype=np.int_),
        colors=np.array([c for _, c, _ in fused_all]),
        params=np.array([p for p, _, _ in fused_all]),
        sigma=np.array([s for _, _, s in fused_all]),
        support=np.array([len(e.weights) for e in entries], dtype=np.int_),
        sigma_floor=floor,
        mismatch_cost=mismatch,
    )
    return world, links
