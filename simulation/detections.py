"""Synthetic detections of a scene from any hemisphere pose, without a renderer or detector.

Each scene object is a cloud of points on its surface (:mod:`.surfaces`). A view projects every
cloud through the hemisphere camera; an object's box is the pixel-edge box of its points that
fall inside the image and are not hidden, rounded like the renderer's silhouettes (a pixel
counts when its centre is covered). Occlusion is approximate: points are binned into cells of
:data:`OCCLUSION_CELL_PX` pixels and a point is hidden when the nearest point of its cell belongs
to another object. The class is the object's shape; the colour is its sRGB colour (0–255), for a
texture the mean of the bitmap. :class:`NoiseModel` adds Gaussian pixel noise to box edges, drops
detections and adds spurious ones, from a seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.contracts.detect import Detection
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.scene import CameraSpec, LoadedScene, MeshObject
from services.optimizer.geometry import FloatArray, PinholeCameras
from services.optimizer.observations import Observation
from simulation.surfaces import srgb8, surface_points, texture_colour

__all__ = ["CLASSES", "OCCLUSION_CELL_PX", "NoiseModel", "SceneSimulator", "SimulatedViews"]

OCCLUSION_CELL_PX: Final = 4.0
CLASSES: Final = ("sphere", "cube", "cylinder", "cone", "mesh")
"""The detector's classes; a detection's ``class_id`` is its index here."""

_MIN_VISIBLE: Final = 0.1
_MIN_SIDE_PX: Final = 2.0


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
            clouds.append(surface_points(obj, mesh))
            if obj.color is not None:
                colours.append(srgb8(obj.color))
            elif obj.texture is not None:
                colours.append(texture_colour(scene.assets[f"objects[{i}].texture"]))
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
