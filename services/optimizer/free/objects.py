"""A scene's objects as 3D point sets, and their projected bounding boxes at any camera.

An object's image box is the bounding box of the projection of its surface. For a point set
``X_k`` whose convex hull contains the surface's outline (a mesh's vertices, a cube's corners, a
cylinder's two rims), the box of the projected points is the box of the projected solid: a box
edge is an extremum of a linear-fractional function of the point, reached at a hull vertex. The
point sets are built here once per scene:

* sphere: a Fibonacci lattice of :data:`SPHERE_POINTS` points on the surface; the silhouette
  box is under-estimated by at most ``ρ (1 - cos δ)`` for the lattice's spacing ``δ ≈ √(4π/N)/2``
  (0.3 % of ρ at 600 points, below 0.1 px for the built-in scenes);
* cube: its eight corners (exact);
* cylinder: two rims of :data:`RIM_POINTS` points (within ``ρ (1 - cos(π/N))``, 0.03 % of ρ);
* cone: the renderer's own 64-segment base polygon and the apex (exact);
* mesh: the convex hull's vertices of the PLY mesh, placed as the renderer places it (exact).

The centroid is the centre of the object's world bounding box, the point the renderer's
annotations project (``RenderAnnotations.objects[i].centroid``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from plyfile import PlyData
from scipy.spatial import ConvexHull

from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    MeshObject,
    SceneObject,
    SceneSpec,
    SphereObject,
)
from services.common.scene_models import object_classes
from services.optimizer.free.srgb import linear
from services.optimizer.geometry import FloatArray

__all__ = [
    "CONE_SEGMENTS",
    "NEAR_DEPTH",
    "RIM_POINTS",
    "SPHERE_POINTS",
    "SceneObjects",
    "project_boxes",
    "scene_objects",
]

SPHERE_POINTS: Final = 600
RIM_POINTS: Final = 128
CONE_SEGMENTS: Final = 64
"""The renderer's cone is this many-sided pyramid (``renderer/scene_builder.py``)."""
NEAR_DEPTH: Final = 1e-6
"""Depth (scene units) below which a point counts as behind the camera."""


@dataclass(frozen=True)
class SceneObjects:
    """Every object of a scene as the pose solver sees it.

    Attributes
    ----------
    names, labels, shapes : the object's name, its identity class label (as the scene's own
        detector names it, look-alikes sharing one) and its shape (the general model's class).
    centroids : (M, 3) world bounding-box centres, scene units.
    points : (P, 3) every object's points, object after object, scene units.
    starts : (M,) index of each object's first point in ``points`` (for ``np.*.reduceat``).
    radius : the scene camera's hemisphere radius, the scale of position errors.
    fov_deg : the scene camera's horizontal field of view.
    colors : (M, 3) each object's linear-RGB colour from the scene file, or its texture's
        mean; NaN when neither is known; None when unknown.
    """

    names: tuple[str, ...]
    labels: tuple[str, ...]
    shapes: tuple[str, ...]
    centroids: FloatArray
    points: FloatArray
    starts: NDArray[np.intp]
    radius: float
    fov_deg: float
    colors: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.names)

    def owners(self) -> NDArray[np.intp]:
        """(P,) the object index of every point."""
        counts = np.diff(np.append(self.starts, len(self.points)))
        return np.repeat(np.arange(len(self.names)), counts)

    def subset(self, keep: ArrayLike) -> SceneObjects:
        """The objects ``keep`` (indices, in that order; repeats allowed)."""
        idx = np.asarray(keep, dtype=np.intp).reshape(-1)
        owners = self.owners()
        chunks = [self.points[owners == i] for i in idx]
        sizes = np.array([len(c) for c in chunks], dtype=np.intp)
        return SceneObjects(
            names=tuple(self.names[i] for i in idx),
            labels=tuple(self.labels[i] for i in idx),
            shapes=tuple(self.shapes[i] for i in idx),
            centroids=self.centroids[idx],
            points=np.concatenate(chunks) if chunks else np.zeros((0, 3)),
            starts=np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp),
            radius=self.radius,
            fov_deg=self.fov_deg,
            colors=None if self.colors is None else self.colors[idx],
        )

    def moved(self, rotation: ArrayLike, translation: ArrayLike) -> SceneObjects:
        """The same objects moved rigidly, ``X' = R X + t`` (for metamorphic tests and scenes
        given in another frame)."""
        r = np.asarray(rotation, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64)
        return SceneObjects(
            names=self.names,
            labels=self.labels,
            shapes=self.shapes,
            centroids=self.centroids @ r.T + t,
            points=self.points @ r.T + t,
            starts=self.starts,
            radius=self.radius,
            fov_deg=self.fov_deg,
            colors=self.colors,
        )


def _yaw_matrix(yaw_deg: float) -> FloatArray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _fibonacci_sphere(count: int) -> FloatArray:
    """``count`` unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    ring = np.sqrt(1.0 - z * z)
    angle = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([ring * np.cos(angle), ring * np.sin(angle), z], axis=1)


def _rim(radius: float, height: float, count: int, yaw_deg: float = 0.0) -> FloatArray:
    a = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False) + math.radians(yaw_deg)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(count, height)], axis=1)


def _mesh_points(obj: MeshObject, path: Path) -> FloatArray:
    """The hull vertices of a PLY mesh placed as the renderer places it:
    ``T(x, y, 0) · Rz(yaw) · S(scale) · T(-c)``, c the bottom centre of its bounding box.

    Read with plyfile here: the project's PLY module (``scene_assets.ply``) sits above the
    services, which may not import it.
    """
    vertex = PlyData.read(str(path))["vertex"]
    local = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    lo, hi = local.min(axis=0), local.max(axis=0)
    bottom = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    world = (local - bottom) * obj.scale @ _yaw_matrix(obj.yaw_deg).T
    world[:, :2] += obj.position
    hull = ConvexHull(world)
    points: FloatArray = world[np.sort(hull.vertices)]
    return points


def _object_points(obj: SceneObject, mesh_file: Path | None) -> FloatArray:
    x, y = obj.position
    foot = np.array([x, y, 0.0])
    local: FloatArray
    if isinstance(obj, SphereObject):
        local = obj.radius * (_fibonacci_sphere(SPHERE_POINTS) + [0.0, 0.0, 1.0])
    elif isinstance(obj, CubeObject):
        corners = np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (0, 2)], dtype=np.float64
        )
        local = (corners * obj.size / 2.0) @ _yaw_matrix(obj.yaw_deg).T
    elif isinstance(obj, CylinderObject):
        rim = _rim(obj.radius, 0.0, RIM_POINTS, obj.yaw_deg)
        local = np.concatenate([rim, rim + [0.0, 0.0, obj.height]])
    elif isinstance(obj, ConeObject):
        base = _rim(obj.radius, 0.0, CONE_SEGMENTS, obj.yaw_deg)
        local = np.concatenate([base, [[0.0, 0.0, obj.height]]])
    else:
        return _mesh_file_points(obj, mesh_file)
    return foot + local


def _mesh_file_points(obj: SceneObject, mesh_file: Path | None) -> FloatArray:
    if mesh_file is None or not isinstance(obj, MeshObject):
        raise ValueError(f"mesh object {obj.name!r} needs its PLY file (the scene's assets)")
    return _mesh_points(obj, mesh_file)


def scene_objects(spec: SceneSpec, assets: Mapping[str, Path] | None = None) -> SceneObjects:
    """The objects of ``spec`` as point sets (module docstring).

    Parameters
    ----------
    spec : the scene file.
    assets : the scene's resolved asset files keyed by field (``LoadedScene.assets``:
        ``objects[3].file`` → path); needed only when the scene has meshes.
    """
    files = assets or {}
    label_of = {name: c.label for c in object_classes(spec) for name in c.objects}
    chunks, centroids = [], []
    for i, obj in enumerate(spec.objects):
        pts = _object_points(obj, files.get(f"objects[{i}].file"))
        chunks.append(pts)
        centroids.append((pts.min(axis=0) + pts.max(axis=0)) / 2.0)
        if isinstance(obj, SphereObject):  # the lattice misses the poles: the exact centre
            centroids[-1] = np.array([*obj.position, obj.radius])
        elif not isinstance(obj, MeshObject):
            centroids[-1][:2] = obj.position
    sizes = np.array([len(c) for c in chunks], dtype=np.intp)
    return SceneObjects(
        names=tuple(o.name for o in spec.objects),
        labels=tuple(label_of[o.name] for o in spec.objects),
        shapes=tuple(o.shape for o in spec.objects),
        centroids=np.array(centroids),
        points=np.concatenate(chunks),
        starts=np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp),
        radius=float(spec.camera.radius),
        fov_deg=float(spec.camera.fov_deg),
        colors=np.array(
            [_colour(o, files.get(f"objects[{i}].texture")) for i, o in enumerate(spec.objects)]
        ),
    )


def _colour(obj: SceneObject, texture: Path | None) -> tuple[float, float, float]:
    """``obj``'s linear-RGB colour: the scene file's, else its ``texture`` bitmap's mean (sRGB
    decoded), else NaN.

    The mean of the whole bitmap stands for the colour its visible part shows, as the
    detector's measure averages an object's pixels. Textured objects (the garden's crate and
    duck) used to have no colour, so a label the detector mistook on them went unchecked.
    Replayed on seven free bench runs (``benchmarks.free_replay --dump``, 1,080 targets): box
    estimates within 5 %/2° 4 more (the own models' 272 → 275 of 440, the general model's
    117 → 118), within 10 %/5° 5 more, none fewer; ``found`` the same 192."""
    if obj.color is not None:
        r, g, b = obj.color
        return float(r), float(g), float(b)
    bgr = None if texture is None else cv2.imread(str(texture), cv2.IMREAD_COLOR)
    if bgr is None:
        return math.nan, math.nan, math.nan
    r, g, b = linear(bgr[..., ::-1].reshape(-1, 3).astype(np.float64) / 255.0).mean(axis=0)
    return float(r), float(g), float(b)


def project_boxes(
    objects: SceneObjects,
    rotation: ArrayLike,
    translation: ArrayLike,
    focal_px: ArrayLike,
    principal_px: ArrayLike,
) -> FloatArray:
    """Unclipped image boxes ``(M, 4)`` ``[x1, y1, x2, y2]`` (pixels) of every object; for a
    stack of poses (``R`` ``(N, 3, 3)``, ``t`` ``(N, 3)``) ``(N, M, 4)``.

    With world-to-camera ``R``, ``t``: ``X_c = R X + t``, ``u = f_x X_c/Z_c + c_x``,
    ``v = f_y Y_c/Z_c + c_y``, and the box is the min and max of ``(u, v)`` over each object's
    points (``np.minimum.reduceat``: one pass over all points). NaN for an object with a point
    at depth ≤ 1e-6 (behind or in the camera's plane: its box is unbounded).
    """
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if len(objects) == 0:
        return np.zeros((*r.shape[:-2], 0, 4))
    cam = objects.points @ np.swapaxes(r, -1, -2) + t[..., np.newaxis, :]
    depth = cam[..., 2]
    behind = np.logical_or.reduceat(depth <= NEAR_DEPTH, objects.starts, axis=-1)
    uv = cam[..., :2] / np.maximum(depth, NEAR_DEPTH)[..., np.newaxis]
    uv = uv * np.asarray(focal_px, dtype=np.float64) + np.asarray(principal_px)
    boxes = np.concatenate(
        [
            np.minimum.reduceat(uv, objects.starts, axis=-2),
            np.maximum.reduceat(uv, objects.starts, axis=-2),
        ],
        axis=-1,
    )
    boxes[behind] = np.nan
    return boxes
