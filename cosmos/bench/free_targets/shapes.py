"""The scene's objects as world points whose projected bounding box is the object's, and that
box projected through a pinhole camera for many objects at once.

The points are the pose solver's own (:func:`services.optimizer.free.scene_objects`: a convex
hull per object, meshes placed as the renderer places them), so that the bench's targets, its
references and the solver see one geometry; here they are regrouped by object with their world
bounding boxes, and projected clipped to the film as a detector's boxes are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.geometry.scene import LoadedScene
from services.optimizer.free import scene_objects

__all__ = ["SceneShapes", "project_boxes", "scene_shapes"]

FloatArray = NDArray[np.float64]
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


def scene_shapes(scene: LoadedScene) -> SceneShapes:
    """Every object of ``scene`` as hull points, in the scene file's order."""
    objects = scene_objects(scene.spec, scene.assets)
    starts = np.append(objects.starts, len(objects.points)).astype(np.int64)
    parts = [objects.points[starts[i] : starts[i + 1]] for i in range(len(objects))]
    return SceneShapes(
        names=objects.names,
        points=objects.points,
        starts=starts,
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
