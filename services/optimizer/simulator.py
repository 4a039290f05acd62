"""An offline search simulator: synthetic detections from a scene file, no renderer.

Each scene object becomes a cloud of points sampled on its surface (spheres, cubes, cylinders and
cones from their parameters, meshes from their PLY vertices, placed as the renderer places them).
A view projects every cloud through the hemisphere camera; an object's box is the pixel-edge box
of its points that fall inside the image and are not hidden, rounded like the renderer's
silhouettes (a pixel counts when its centre is covered). Occlusion is approximate: points are
binned into cells of :data:`OCCLUSION_CELL_PX` pixels and a point is hidden when the nearest point
of its cell belongs to another object. The class is the object's shape; the colour is its sRGB
colour (0–255), for a texture the mean of the bitmap. :class:`NoiseModel` adds Gaussian pixel
noise to box edges, drops detections and adds spurious ones, from a seeded generator.

:func:`run_search` plays a strategy from a start pose until it declares the search done (or a
move limit), feeding it the simulated detections of every pose it visits.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.contracts.detect import Detection
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import (
    CameraSpec,
    ConeObject,
    CubeObject,
    CylinderObject,
    LoadedScene,
    MeshObject,
    SceneObject,
    SphereObject,
)
from services.optimizer.calibration import PaperCalibration
from services.optimizer.geometry import FloatArray, PinholeCameras
from services.optimizer.observations import Observation
from services.optimizer.problem import Plan, SearchProblem, Visit
from services.optimizer.strategies import STRATEGIES

__all__ = [
    "CLASSES",
    "OCCLUSION_CELL_PX",
    "NoiseModel",
    "SceneSimulator",
    "SearchOutcome",
    "SimulatedViews",
    "read_ply_vertices",
    "run_search",
    "srgb8",
]

OCCLUSION_CELL_PX: Final = 4.0
CLASSES: Final = ("sphere", "cube", "cylinder", "cone", "mesh")
"""The detector's classes; a detection's ``class_id`` is its index here."""

_MIN_VISIBLE: Final = 0.1
_MAX_REVISITS: Final = 3
_MIN_SIDE_PX: Final = 2.0


def srgb8(linear: ArrayLike) -> FloatArray:
    """Linear RGB (0–1) to sRGB 0–255 (IEC 61966-2-1 transfer function)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)
    return srgb * 255.0


_PLY_TYPES: Final = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def read_ply_vertices(path: Path) -> FloatArray:
    """The ``x, y, z`` of a PLY file's vertices ``(V, 3)``.

    Reads ASCII and binary PLY whose first element is ``vertex`` with scalar properties (what
    ``tools.make_assets`` writes and most exporters do); anything else raises ``ValueError``.
    """
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    count = -1
    props: list[tuple[str, str]] = []
    element = ""
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            if element == "vertex":
                break
            element = parts[1]
            if element != "vertex":
                raise ValueError(f"{path}: the first element must be 'vertex'")
            count = int(parts[2])
        elif parts[0] == "property" and element == "vertex":
            if parts[1] == "list":
                raise ValueError(f"{path}: list properties on vertices are not supported")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [name for name, _ in props]
    if count < 0 or not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: no vertex positions")
    if fmt == "ascii":
        lines = data[body_start:].decode("ascii").splitlines()[:count]
        table = np.array([[float(v) for v in line.split()[: len(props)]] for line in lines])
        return table[:, [names.index(k) for k in ("x", "y", "z")]].astype(np.float64)
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    if order is None:
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    dtype = np.dtype([(name, order + code) for name, code in props])
    vertices = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
    return np.stack([vertices[k].astype(np.float64) for k in ("x", "y", "z")], axis=-1)


def _fibonacci_sphere(count: int) -> FloatArray:
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * i
    rho = np.sqrt(1.0 - z**2)
    return np.stack([rho * np.cos(azimuth), rho * np.sin(azimuth), z], axis=-1)


def _yaw(points: FloatArray, yaw_deg: float) -> FloatArray:
    a = math.radians(yaw_deg)
    rot = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]])
    out: FloatArray = points @ rot.T
    return out


def _disc(radius: float, z: float, rings: int = 4, per_ring: int = 48) -> FloatArray:
    r = np.repeat(np.linspace(0.0, radius, rings + 1)[1:], per_ring)
    a = np.tile(np.linspace(0.0, 2.0 * math.pi, per_ring, endpoint=False), rings)
    pts = np.stack([r * np.cos(a), r * np.sin(a), np.full_like(r, z)], axis=-1)
    return np.concatenate([pts, [[0.0, 0.0, z]]])


def _surface_points(obj: SceneObject, mesh_file: Path | None) -> FloatArray:
    """Points on the object's surface in world coordinates, placed as the renderer places it."""
    x, y = obj.position
    offset = np.array([x, y, 0.0])
    if isinstance(obj, SphereObject):
        ball: FloatArray = _fibonacci_sphere(800) * obj.radius + np.array([x, y, obj.radius])
        return ball
    if isinstance(obj, CubeObject):
        g = np.linspace(-1.0, 1.0, 12)
        a, b = (m.ravel() for m in np.meshgrid(g, g))
        one = np.ones_like(a)
        faces = [
            np.stack(p, axis=-1)
            for p in (
                (one, a, b),
                (-one, a, b),
                (a, one, b),
                (a, -one, b),
                (a, b, one),
                (a, b, -one),
            )
        ]
        unit = np.concatenate(faces) * (obj.size / 2.0) + np.array([0.0, 0.0, obj.size / 2.0])
        cube: FloatArray = _yaw(unit, obj.yaw_deg) + offset
        return cube
    if isinstance(obj, CylinderObject | ConeObject):
        angles = np.linspace(0.0, 2.0 * math.pi, 48, endpoint=False)
        t = np.linspace(0.0, 1.0, 12)
        aa, tt = (m.ravel() for m in np.meshgrid(angles, t))
        taper = (1.0 - tt) if isinstance(obj, ConeObject) else np.ones_like(tt)
        side = np.stack(
            [obj.radius * taper * np.cos(aa), obj.radius * taper * np.sin(aa), obj.height * tt],
            axis=-1,
        )
        caps = [_disc(obj.radius, 0.0)]
        if isinstance(obj, CylinderObject):
            caps.append(_disc(obj.radius, obj.height))
        solid: FloatArray = _yaw(np.concatenate([side, *caps]), obj.yaw_deg) + offset
        return solid
    if mesh_file is None:
        raise ValueError(f"{obj.name}: a mesh needs its PLY file")
    vertices = read_ply_vertices(mesh_file)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    bottom_centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    mesh: FloatArray = _yaw((vertices - bottom_centre) * obj.scale, obj.yaw_deg) + offset
    return mesh


def _texture_colour(path: Path) -> FloatArray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{path}: cannot read the texture")
    bgr = image.reshape(-1, 3).mean(axis=0)
    return np.asarray(bgr[::-1], dtype=np.float64)


@dataclass(frozen=True)
class SimulatedViews:
    """Noise-free detections of every object in N views.

    Attributes
    ----------
    boxes : ndarray, shape (N, M, 4)
        Pixel-edge boxes of the visible parts, NaN when not detected.
    visible : ndarray of bool, shape (N, M)
        Whether the object is detected (enough of it visible, box at least 2 px a side).
    fraction : ndarray, shape (N, M)
        Unhidden fraction of the object's points that fall inside the image.
    """

    boxes: FloatArray
    visible: NDArray[np.bool_]
    fraction: FloatArray


@dataclass(frozen=True)
class NoiseModel:
    """Detector imperfections for simulated detections.

    Attributes
    ----------
    pixel_sigma : float
        Standard deviation of Gaussian noise on each box edge, pixels.
    miss_rate : float
        Probability that a visible object is not detected.
    spurious_rate : float
        Probability that an image gets one extra detection of a random scene class, box and
        colour.
    colour_sigma : float
        Standard deviation of noise on each sRGB channel (0–255).
    """

    pixel_sigma: float = 0.0
    miss_rate: float = 0.0
    spurious_rate: float = 0.0
    colour_sigma: float = 0.0

    @property
    def clean(self) -> bool:
        return (
            self.pixel_sigma == 0.0
            and self.miss_rate == 0.0
            and self.spurious_rate == 0.0
            and self.colour_sigma == 0.0
        )


@dataclass
class SceneSimulator:
    """Synthetic detections of a scene's objects from any hemisphere pose."""

    camera: CameraSpec
    labels: tuple[str, ...]
    colours: FloatArray
    points: FloatArray
    owners: NDArray[np.int_]
    occlusion: bool = True
    _cache: dict[tuple[float, float, float], SimulatedViews] = field(default_factory=dict)
    _clean: dict[tuple[int, int], Observation] = field(default_factory=dict)

    @classmethod
    def from_scene(cls, scene: LoadedScene, *, occlusion: bool = True) -> SceneSimulator:
        """Sample every object of a loaded scene (meshes and textures from its assets)."""
        clouds, colours = [], []
        for i, obj in enumerate(scene.spec.objects):
            mesh = scene.assets.get(f"objects[{i}].file") if isinstance(obj, MeshObject) else None
            clouds.append(_surface_points(obj, mesh))
            if obj.color is not None:
                colours.append(srgb8(obj.color))
            elif obj.texture is not None:
                colours.append(_texture_colour(scene.assets[f"objects[{i}].texture"]))
            else:
                colours.append(np.full(3, np.nan))
        return cls(
            camera=scene.spec.camera,
            labels=tuple(obj.shape for obj in scene.spec.objects),
            colours=np.array(colours),
            points=np.concatenate(clouds),
            owners=np.concatenate([np.full(len(c), i) for i, c in enumerate(clouds)]),
            occlusion=occlusion,
        )

    @property
    def object_count(self) -> int:
        return len(self.labels)

    def views(self, theta_deg: ArrayLike, phi_deg: ArrayLike) -> SimulatedViews:
        """Noise-free boxes of every object from poses (θ, φ) in degrees (flattened)."""
        cams = PinholeCameras.at(theta_deg, phi_deg, self.camera)
        pixels, depth = cams.project(self.points)
        n, m = len(cams), self.object_count
        w, h = self.camera.width, self.camera.height
        inside = (
            np.isfinite(pixels[..., 0])
            & (pixels[..., 0] >= 0.0)
            & (pixels[..., 0] < w)
            & (pixels[..., 1] >= 0.0)
            & (pixels[..., 1] < h)
        )
        shown = inside.copy()
        if self.occlusion:
            shown &= self._unhidden(pixels, depth, inside)
        owners = np.broadcast_to(self.owners, inside.shape)
        total = np.zeros((n, m))
        seen = np.zeros((n, m))
        rows = np.broadcast_to(np.arange(n)[:, None], inside.shape)
        np.add.at(total, (rows[inside], owners[inside]), 1.0)
        np.add.at(seen, (rows[shown], owners[shown]), 1.0)
        big = np.inf
        lo = np.full((n, m, 2), big)
        hi = np.full((n, m, 2), -big)
        for axis in range(2):
            np.minimum.at(lo[..., axis], (rows[shown], owners[shown]), pixels[..., axis][shown])
            np.maximum.at(hi[..., axis], (rows[shown], owners[shown]), pixels[..., axis][shown])
        # Pixel-edge boxes of the pixels whose centres the silhouette covers.
        x1 = np.clip(np.ceil(lo[..., 0] - 0.5), 0, w)
        y1 = np.clip(np.ceil(lo[..., 1] - 0.5), 0, h)
        x2 = np.clip(np.floor(hi[..., 0] - 0.5) + 1.0, 0, w)
        y2 = np.clip(np.floor(hi[..., 1] - 0.5) + 1.0, 0, h)
        boxes = np.stack([x1, y1, x2, y2], axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            fraction = np.where(total > 0, seen / total, 0.0)
        visible = (
            (seen > 0)
            & (fraction >= _MIN_VISIBLE)
            & (x2 - x1 >= _MIN_SIDE_PX)
            & (y2 - y1 >= _MIN_SIDE_PX)
        )
        boxes[~visible] = np.nan
        return SimulatedViews(boxes=boxes, visible=visible, fraction=fraction)

    def _unhidden(
        self, pixels: FloatArray, depth: FloatArray, inside: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """Points not hidden by another object (cell-binned z-buffer, module docstring)."""
        n, p = inside.shape
        cols = int(math.ceil(self.camera.width / OCCLUSION_CELL_PX))
        rows_ = int(math.ceil(self.camera.height / OCCLUSION_CELL_PX))
        cx = np.floor(np.nan_to_num(pixels[..., 0]) / OCCLUSION_CELL_PX).astype(np.int64)
        cy = np.floor(np.nan_to_num(pixels[..., 1]) / OCCLUSION_CELL_PX).astype(np.int64)
        cell = np.arange(n)[:, None] * (cols * rows_) + np.clip(cy, 0, rows_ - 1) * cols
        cell = cell + np.clip(cx, 0, cols - 1)
        cells = cell[inside]
        d = depth[inside]
        nearest = np.full(n * cols * rows_, np.inf)
        np.minimum.at(nearest, cells, d)
        front = d <= nearest[cells]
        owner_of = np.full(n * cols * rows_, -1)
        owners = np.broadcast_to(self.owners, inside.shape)[inside]
        owner_of[cells[front]] = owners[front]
        keep = np.zeros_like(inside)
        keep[inside] = owner_of[cells] == owners
        return keep

    def grid_views(self, grid: HemisphereGrid) -> SimulatedViews:
        """Noise-free views of every grid pose in flat order (computed once per grid)."""
        key = (grid.angle_step_deg, float(grid.theta_deg[0]), float(grid.theta_deg[-1]))
        if key not in self._cache:
            self._cache[key] = self.views(grid.theta_deg, grid.phi_deg)
        return self._cache[key]

    def clean_observation(self, views: SimulatedViews, index: int) -> Observation:
        """The noise-free observation of view ``index``, one shared object per view (so caches
        keyed by observation identity hit)."""
        key = (id(views), index)
        if key not in self._clean:
            self._clean[key] = self.observe(views, index)
        return self._clean[key]

    def observe(
        self,
        views: SimulatedViews,
        index: int,
        noise: NoiseModel | None = None,
        rng: np.random.Generator | None = None,
    ) -> Observation:
        """The detections of view ``index`` of ``views``, with ``noise`` drawn from ``rng``."""
        keep = np.flatnonzero(views.visible[index])
        boxes = views.boxes[index, keep].copy()
        colours = self.colours[keep].copy()
        labels = [self.labels[i] for i in keep]
        if noise is not None and not noise.clean:
            if rng is None:
                raise ValueError("noise needs a random generator")
            w, h = self.camera.width, self.camera.height
            boxes += rng.normal(0.0, noise.pixel_sigma, boxes.shape)
            boxes = np.clip(boxes, 0.0, [w, h, w, h])
            colours = np.clip(colours + rng.normal(0.0, noise.colour_sigma, colours.shape), 0, 255)
            kept = (rng.random(len(labels)) >= noise.miss_rate) & (
                (boxes[:, 2] - boxes[:, 0] > 1.0) & (boxes[:, 3] - boxes[:, 1] > 1.0)
            )
            boxes, colours = boxes[kept], colours[kept]
            labels = [label for label, k in zip(labels, kept, strict=True) if k]
            if rng.random() < noise.spurious_rate:
                size = rng.uniform(8.0, 40.0, 2)
                x1 = rng.uniform(0.0, w - size[0])
                y1 = rng.uniform(0.0, h - size[1])
                boxes = np.vstack([boxes, [x1, y1, x1 + size[0], y1 + size[1]]])
                colours = np.vstack([colours, rng.uniform(0.0, 255.0, 3)])
                labels.append(str(rng.choice(sorted(set(self.labels)))))
        return Observation.from_arrays(labels, boxes, colours)

    def detections(self, observation: Observation) -> tuple[Detection, ...]:
        """An observation as detection messages (camera pixels)."""
        out = []
        for label, box, colour, conf in zip(
            observation.labels,
            observation.boxes,
            observation.colors,
            observation.confidence,
            strict=True,
        ):
            rgb = (
                None
                if np.isnan(colour).any()
                else (float(colour[0]), float(colour[1]), float(colour[2]))
            )
            out.append(
                Detection(
                    label=label,
                    class_id=CLASSES.index(label) if label in CLASSES else len(CLASSES),
                    confidence=float(min(max(conf, 0.0), 1.0)),
                    box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                    color=rgb,
                )
            )
        return tuple(out)


@dataclass(frozen=True)
class SearchOutcome:
    """One simulated search.

    Attributes
    ----------
    target, start, final : int
        Flat grid indices of the target, the start and where the camera ended.
    arrival : int or None
        Moves after the start view until the camera first sat at the target (None: never).
    moves : int
        Moves made until the strategy declared the search done (or the move limit).
    done : bool
        Whether the strategy declared the search done.
    ambiguous : bool
        Whether any answer on the way was flagged ambiguous.
    """

    target: int
    start: int
    final: int
    arrival: int | None
    moves: int
    done: bool
    ambiguous: bool

    @property
    def success(self) -> bool:
        """Declared done with the camera at the target."""
        return self.done and self.final == self.target


def run_search(
    strategy: str,
    simulator: SceneSimulator,
    grid: HemisphereGrid,
    target: int,
    start: int,
    *,
    calibration: PaperCalibration | None = None,
    noise: NoiseModel | None = None,
    rng: np.random.Generator | None = None,
    tolerance_px: float = 1.0,
    max_moves: int = 60,
    cache: dict[Hashable, Plan] | None = None,
) -> SearchOutcome:
    """Play ``strategy`` from ``start`` towards ``target`` on simulated detections.

    ``cache`` (for strategies with a decision key, without noise) memoises plans per
    (decision key, target), exact because such a plan depends on nothing else. The
    search stops at ``max_moves`` or when a pose would be entered a fourth time (a cycle).
    """
    views = simulator.grid_views(grid)
    spec = STRATEGIES[strategy]
    if cache is not None and (spec.decision_key is None or not (noise is None or noise.clean)):
        raise ValueError("plans can be cached only for strategies with a decision key, no noise")

    clean = noise is None or noise.clean

    def observe(flat: int) -> Observation:
        if clean:
            return simulator.clean_observation(views, flat)
        return simulator.observe(views, flat, noise, rng)

    def visit(flat: int) -> Visit:
        return Visit(flat, float(grid.theta_deg[flat]), float(grid.phi_deg[flat]), observe(flat))

    target_view = observe(target)
    history = [visit(start)]
    arrival = 0 if start == target else None
    moves = 0
    ambiguous = False
    visits = {start: 1}
    while True:
        problem = SearchProblem(
            grid=grid,
            camera=simulator.camera,
            target=target_view,
            history=tuple(history),
            tolerance_px=tolerance_px,
            calibration=calibration,
        )
        key = None
        if cache is not None and spec.decision_key is not None:
            key = (spec.decision_key(problem), target)
        plan = cache.get(key) if cache is not None and key is not None else None
        if plan is None:
            plan = spec.plan(problem)
            if cache is not None and key is not None:
                cache[key] = plan
        ambiguous |= plan.ambiguous
        if plan.done or moves >= max_moves:
            break
        visits[plan.next_flat] = visits.get(plan.next_flat, 0) + 1
        if visits[plan.next_flat] > _MAX_REVISITS:
            break  # cycling: the strategy cannot make progress
        moves += 1
        history.append(visit(plan.next_flat))
        if arrival is None and plan.next_flat == target:
            arrival = moves
    return SearchOutcome(
        target=target,
        start=start,
        final=history[-1].flat,
        arrival=arrival,
        moves=moves,
        done=plan.done,
        ambiguous=ambiguous,
    )
