"""The baseline a user would write first, on what the search's detector saw.

Each of the target's detections (the search's ``target_detections``) is paired with the scene
object its label names when the label fits exactly one object (the scene's identity class, the
object's shape for the general model, or its name: :func:`~services.optimizer.free.hypotheses.
compatibility`), the most confident detection per object; look-alike labels are left out, as a
user pairing by name would. Then OpenCV's ``cv2.solvePnPRansac`` with its defaults runs on the
box centres against the objects' 3D centres (:func:`cosmos.bench.free_targets.solve.
baseline_pnp`), with the intrinsics the search was given, else the scene camera's fov: what a
user knows. Fewer than 4 pairs give no pose (OpenCV refuses).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.solve import baseline_pnp
from services.common.geometry.camera import focal_length_px
from services.optimizer.free import SceneObjects
from services.optimizer.free.hypotheses import compatibility

__all__ = ["baseline_of_detections"]


def baseline_of_detections(
    objects: SceneObjects,
    detections: Sequence[Mapping[str, Any]],
    size: tuple[int, int],
    fov_deg: float,
) -> Estimate | None:
    """The baseline's pose (module docstring) from ``detections`` (the search's JSON) on an
    image of ``size`` (width, height) taken with a horizontal ``fov_deg``."""
    labels = tuple(str(d["label"]) for d in detections)
    fits = compatibility(objects, labels)
    best: dict[int, int] = {}
    for i, row in enumerate(fits):
        if row.sum() != 1:
            continue
        j = int(np.argmax(row))
        if j not in best or detections[i]["confidence"] > detections[best[j]]["confidence"]:
            best[j] = i
    if len(best) < 4:
        return None
    pairs = sorted(best.items())
    boxes = np.array([detections[i]["box"] for _, i in pairs], dtype=np.float64)
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2.0
    width, height = size
    focal = focal_length_px(fov_deg, width)
    intrinsics = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0, 0, 1.0]])
    centroids = objects.centroids[[j for j, _ in pairs]]
    return baseline_pnp(centroids, centres, intrinsics, fov_deg)
