"""Scene objects as point clouds on their surfaces, and their colours, for the simulator.

Spheres, cubes, cylinders and cones are sampled from their parameters, meshes take their PLY
vertices; every cloud is placed as the renderer places the object (a mesh's bounding-box bottom
centre at the object's position, scaled, then yawed).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike

from scene_assets import read_ply_vertices
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    SceneObject,
    SphereObject,
)
from services.optimizer.geometry import FloatArray

__all__ = ["srgb8", "surface_points", "texture_colour"]


def srgb8(linear: ArrayLike) -> FloatArray:
    """Linear RGB (0–1) to sRGB 0–255 (IEC 61966-2-1 transfer function)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)
    return srgb * 255.0


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


def surface_points(obj: SceneObject, mesh_file: Path | None) -> FloatArray:
    """Points ``(P, 3)`` on the object's surface in world coordinates, placed as the renderer
    places it; a mesh needs its PLY file."""
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
    vertices = read_ply_vertices(mesh_file).astype(np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    bottom_centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    mesh: FloatArray = _yaw((vertices - bottom_centre) * obj.scale, obj.yaw_deg) + offset
    return mesh


def texture_colour(path: Path) -> FloatArray:
    """The mean sRGB colour (0–255) of a texture bitmap ``(3,)``."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{path}: cannot read the texture")
    bgr = image.reshape(-1, 3).mean(axis=0)
    return np.asarray(bgr[::-1], dtype=np.float64)
