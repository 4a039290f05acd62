"""Drone views of a scene for the detectors' training sets: anywhere, looking anywhere at the
objects, mostly down, rolled, through another lens, as the free bench draws its targets
(``cosmos/bench/free_targets/draw.py``).

A camera at distance ``d`` from a look point ``p`` on the ground, at elevation ``e`` and azimuth
``a``, stands at ``p + d (cos e cos a, cos e sin a, sin e)`` and looks back along that ray.
"""

from __future__ import annotations

import numpy as np

from services.common.geometry.free_camera import FreeCamera, orbit_position
from services.common.geometry.pose import Pose
from services.common.geometry.scene import LoadedScene
from services.renderer.free_view import FreeView
from services.renderer.view import resolve_free_camera

__all__ = [
    "DRONE_DISTANCE",
    "DRONE_FOV_SPREAD",
    "DRONE_NADIR_SHARE",
    "DRONE_ROLL_DEG",
    "drone_camera",
    "engine_view",
]

DRONE_DISTANCE = (0.4, 1.6)
"""A drone view's distance from the point it looks at, in scene radii…"""
DRONE_NADIR_SHARE = 0.25
"""…the share of them that look straight down (the others at 10–89° of elevation)…"""
DRONE_ROLL_DEG = 25.0
"""…their roll, uniform within ±this…"""
DRONE_FOV_SPREAD = 0.3
"""…and their horizontal fov, uniform within ±this share of the scene camera's."""


def drone_camera(scene: LoadedScene, rng: np.random.Generator) -> FreeCamera:
    """A drone's view of ``scene``: looking at a point of the objects' footprint (grown by a
    tenth of the radius) from :data:`DRONE_DISTANCE`, at an elevation of 10–89° or straight
    down, any azimuth, rolled and zoomed (module docstring)."""
    r = scene.spec.camera.radius
    xy = np.array([o.position for o in scene.spec.objects], dtype=np.float64).reshape(-1, 2)
    lo, hi = xy.min(axis=0) - 0.1 * r, xy.max(axis=0) + 0.1 * r
    look = rng.uniform(lo, hi)
    distance = float(rng.uniform(*DRONE_DISTANCE)) * r
    nadir = rng.uniform() < DRONE_NADIR_SHARE
    elevation = 90.0 if nadir else float(rng.uniform(10.0, 89.0))
    azimuth = float(rng.uniform(0.0, 360.0))
    spread = float(rng.uniform(1.0 - DRONE_FOV_SPREAD, 1.0 + DRONE_FOV_SPREAD))
    point = (float(look[0]), float(look[1]), 0.0)
    return FreeCamera(
        position=orbit_position(point, distance, elevation, azimuth),
        yaw_deg=(azimuth + 180.0) % 360.0,
        pitch_deg=elevation,
        roll_deg=float(rng.uniform(-DRONE_ROLL_DEG, DRONE_ROLL_DEG)),
        fov_deg=min(scene.spec.camera.fov_deg * spread, 120.0),
    )


def engine_view(
    scene: LoadedScene, pose: Pose | FreeCamera, width: int, height: int
) -> Pose | FreeView:
    """``pose`` as the render engine takes it on a ``width`` x ``height`` film: a hemisphere
    pose as it is, a free camera resolved (:func:`~services.renderer.view.resolve_free_camera`)."""
    if isinstance(pose, FreeCamera):
        return resolve_free_camera(scene, pose, width, height)
    return pose
