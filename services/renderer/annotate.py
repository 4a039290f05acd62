"""Per-object silhouette statistics from per-pixel object ids (pure numpy), and the objects'
annotations made of them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.contracts.render import ObjectAnnotation
from services.common.geometry.scene import SceneObject

__all__ = ["Silhouettes", "object_annotations", "silhouettes"]


@dataclass(frozen=True)
class Silhouettes:
    """Pixel counts ``(N,)`` and boxes ``(N, 4)`` as ``[x1, y1, x2, y2]`` in pixel edges
    (a box covers pixels x1 <= x < x2); rows of objects with no pixel are NaN."""

    pixels: NDArray[np.int64]
    boxes: NDArray[np.float64]

    def box(self, index: int) -> tuple[float, float, float, float] | None:
        if self.pixels[index] == 0:
            return None
        x1, y1, x2, y2 = (float(v) for v in self.boxes[index])
        return (x1, y1, x2, y2)


def silhouettes(object_ids: NDArray[np.integer], count: int) -> Silhouettes:
    """Count the pixels and bound the silhouette of objects ``0 .. count-1`` in an id image.

    ``object_ids`` is ``(H, W)`` with the object index per pixel and -1 where none is seen.
    """
    ids = np.asarray(object_ids)
    ys, xs = np.nonzero((ids >= 0) & (ids < count))
    owners = ids[ys, xs].astype(np.int64)
    pixels = np.bincount(owners, minlength=count).astype(np.int64)
    big = np.iinfo(np.int64).max
    x1 = np.full(count, big)
    y1 = np.full(count, big)
    x2 = np.full(count, -1)
    y2 = np.full(count, -1)
    np.minimum.at(x1, owners, xs)
    np.minimum.at(y1, owners, ys)
    np.maximum.at(x2, owners, xs)
    np.maximum.at(y2, owners, ys)
    boxes = np.stack([x1, y1, x2 + 1, y2 + 1], axis=1).astype(np.float64)
    boxes[pixels == 0] = np.nan
    return Silhouettes(pixels=pixels, boxes=boxes)


def object_annotations(
    objects: Sequence[SceneObject],
    visible: Silhouettes,
    full: Silhouettes,
    centroids: NDArray[np.float64],
    projected: NDArray[np.float64],
) -> tuple[ObjectAnnotation, ...]:
    """Each object's annotation from its visible silhouette (in the whole scene), its full one
    (alone, unoccluded), its bounding-box centroid and that centroid's projection (NaN, behind
    the camera: none)."""
    annotations = []
    for index, obj in enumerate(objects):
        whole = int(full.pixels[index])
        seen = int(min(visible.pixels[index], whole)) if whole else int(visible.pixels[index])
        annotations.append(
            ObjectAnnotation(
                name=obj.name,
                shape=obj.shape,
                position=(obj.position[0], obj.position[1], 0.0),
                centroid=tuple(float(v) for v in centroids[index]),
                box=visible.box(index),
                visible_pixels=int(visible.pixels[index]),
                full_box=full.box(index),
                full_pixels=whole,
                visible_fraction=seen / whole if whole else 0.0,
                projected_center=(
                    (float(projected[index, 0]), float(projected[index, 1]))
                    if np.all(np.isfinite(projected[index]))
                    else None
                ),
            )
        )
    return tuple(annotations)
