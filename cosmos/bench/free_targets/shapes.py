"""The scene's objects as world points whose projected bounding box is the object's, and that
box projected through a pinhole camera for many objects at once.

A projected bounding box only depends on the object's convex hull, so each object is the hull's
points: a cube's 8 corners; a cylinder's two rim circles; a cone's base ring (the renderer's
:data:`~services.renderer.scene_builder.CONE_SEGMENTS`-gon) and apex; a sphere's surface sampled
on a Fibonacci lattice (2,000 points: the silhouette's extent is then short by at most
r (1 - cos(δ/2)) ≈ 0.1 % of r, δ ≈ 0.08 rad the lattice's spacing); a mesh's PLY vertices on its
convex hull, placed as the renderer places them: ``T(x, y, 0) · Rz(yaw) · S(scale) · T(-c)``,
c the bottom centre of the PLY's bounding box (:mod:`services.renderer.scene_builder`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from scene_assets.ply import read_ply_vertices
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    LoadedScene,
    MeshObject,
    SceneObject,
    SphereObject,
)

__all__ = ["SPHERE_POINTS", "SceneShapes", "project_boxes", "scene_shapes"]

FloatArray = NDArray[np.float64]
SPHERE_POINTS = 2000
RIM_POINTS = 256
CONE_SEGMENTS = 64  # as services.renderer.scene_builder.CONE_SEGMENTS (cosmos may not import it)
MIN_DEPTH = 1e-3
"""Points closer to (or behind) the image plane count at this depth, so a fit never divides by
zero; a camera in a search of its own never has an object behind it."""


@dataclass(frozen=True)
class SceneShapes:
    """Every object's hull points, stacked.

    Attributes
    ----------
    names : the objects' names, in the scene file's order.
    points : (P, 3) world points, scene units; object ``i`` owns ``points[starts[i]:starts[i+1]]``.
    starts : (N + 1,) offsets of each object's points.
    lo, hi : (N, 3) each object's world bounding box.
    """

    names: tuple[str, ...]
    points: FloatArray
    starts: NDArray[np.int64]
    lo: FloatArray
    hi: FloatArray

    @property
    def centroids(self) -> FloatArray:
        """(N, 3) bounding-box centres (what annotations call ``centroid``)."""
        return (self.lo + self.hi) / 2.0

    def subset(self, names: tuple[str, ...]) -> SceneShapes:
        """These objects only, in the order of ``names``."""
        index = [self.names.index(name) for name in names]
        parts = [self.points[self.starts[i] : self.starts[i + 1]] for i in index]
        sizes = np.array([0, *(len(p) for p in parts)], dtype=np.int64)
        return SceneShapes(
            names=names,
            points=np.concatenate(parts) if parts else np.zeros((0, 3)),
            starts=np.cumsum(sizes),
            lo=self.lo[index],
            hi=self.hi[index],
        )


def _rz(yaw_deg: float) -> FloatArray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ring(radius: float, z: float, count: int, yaw_deg: float = 0.0) -> FloatArray:
    angles = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False) + math.radians(yaw_deg)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(count, z)], axis=1)


def _fibonacci_sphere(count: int) -> FloatArray:
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    angle = math.pi * (1.0 + math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)


def object_points(scene: LoadedScene, index: int) -> FloatArray:
    """World hull points of object ``index`` (module docstring), ``(K, 3)``."""
    obj: SceneObject = scene.spec.objects[index]
    x, y = obj.position
    base = np.array([x, y, 0.0])
    local: FloatArray
    if isinstance(obj, SphereObject):
        local = obj.radius * (_fibonacci_sphere(SPHERE_POINTS) + np.array([0.0, 0.0, 1.0]))
    elif isinstance(obj, CubeObject):
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (0, 2)])
        local = obj.size / 2.0 * corners @ _rz(obj.yaw_deg).T
    elif isinstance(obj, CylinderObject):
        rims = [_ring(obj.radius, z, RIM_POINTS, obj.yaw_deg) for z in (0.0, obj.height)]
        local = np.concatenate(rims)
    elif isinstance(obj, ConeObject):
        ring = _ring(obj.radius, 0.0, CONE_SEGMENTS, obj.yaw_deg)
        local = np.concatenate([ring, [[0.0, 0.0, obj.height]]])
    elif isinstance(obj, MeshObject):
        vertices = read_ply_vertices(scene.assets[f"objects[{index}].file"]).astype(np.float64)
        vertices = vertices[ConvexHull(vertices).vertices]
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        bottom_centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
        local = obj.scale * (vertices - bottom_centre) @ _rz(obj.yaw_deg).T
    else:
        raise TypeError(f"unknown object shape {obj.shape}")
    placed: FloatArray = base + local
    return placed


def scene_shapes(scene: LoadedScene) -> SceneShapes:
    """Every object of ``scene`` as hull points (:func:`object_points`)."""
    parts = [object_points(scene, i) for i in range(len(scene.spec.objects))]
    sizes = np.array([0, *(len(p) for p in parts)], dtype=np.int64)
    return SceneShapes(
        names=tuple(obj.name for obj in scene.spec.objects),
        points=np.concatenate(parts),
        starts=np.cumsum(sizes),
        lo=np.array([p.min(axis=0) for p in parts]),
        hi=np.array([p.max(axis=0) for p in parts]),
    )


def project_boxes(
    shapes: SceneShapes,
    rotation: FloatArray,
    translation: FloatArray,
    intrinsics: FloatArray,
    film: tuple[int, int] | None = None,
) -> FloatArray:
    """Each object's projected bounding box ``(N, 4)`` as ``[x1, y1, x2, y2]`` pixel edges.

    ``rotation`` and ``translation`` are the world-to-camera ``R``, ``t`` (OpenCV axes),
    ``intrinsics`` the 3x3 ``K``; a point X lands at ``K (R X + t)`` over its depth. With
    ``film`` (width, height) the boxes are clipped to the image, as a detector's are.
    """
    cam = shapes.points @ rotation.T + translation
    depth = np.maximum(cam[:, 2], MIN_DEPTH)
    u = intrinsics[0, 0] * cam[:, 0] / depth + intrinsics[0, 2]
    v = intrinsics[1, 1] * cam[:, 1] / depth + intrinsics[1, 2]
    starts = shapes.starts[:-1]
    boxes = np.stack(
        [
            np.minimum.reduceat(u, starts),
            np.minimum.reduceat(v, starts),
            np.maximum.reduceat(u, starts),
            np.maximum.reduceat(v, starts),
        ],
        axis=1,
    )
    if film is not None:
        width, height = film
        boxes = np.clip(boxes, 0.0, np.array([width, height, width, height], dtype=np.float64))
    return boxes
