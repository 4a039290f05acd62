"""Poses from one or two usable detections, where no minimal set exists: edge fits from a ring
of start views around the scene (:data:`FEW_STARTS_DEG`), over the detections' assignments.
The solver (:mod:`.solve`) answers them ``ambiguous``, never ``found``.
"""

from __future__ import annotations

import itertools
import math
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.geometry.free_camera import look_at_angles, rotation_of_yaw_pitch_roll
from services.optimizer.free.objects import SceneObjects
from services.optimizer.free.refine import Intrinsics, PoseFit, refine_edges
from services.optimizer.geometry import FloatArray

__all__ = ["FEW_STARTS_DEG", "MAX_FEW_ASSIGNMENTS", "few_detections", "few_fits", "start_view"]

FEW_STARTS_DEG: Final = tuple((theta, phi) for theta in (30.0, 60.0) for phi in range(0, 360, 90))
"""(θ, φ) of the start views at the scene radius when fewer than three detections are usable."""
MAX_FEW_ASSIGNMENTS: Final = 4


def start_view(
    theta_deg: float, phi_deg: float, radius: float, target: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """World-to-camera ``(rvec, tvec)`` of a camera at (θ, φ) on the sphere of ``radius`` about
    ``target``, looking at it."""
    theta, phi = math.radians(theta_deg), math.radians(phi_deg)
    centre = target + radius * np.array(
        [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]
    )
    yaw, pitch = look_at_angles(centre, target)
    rotation = rotation_of_yaw_pitch_roll(yaw, pitch, 0.0).T
    rvec, _ = cv2.Rodrigues(rotation)
    return np.asarray(rvec, dtype=np.float64).reshape(3), -rotation @ centre


def few_fits(
    objects: SceneObjects,
    boxes: FloatArray,
    masks: NDArray[np.bool_],
    compatible: NDArray[np.bool_],
    usable: NDArray[np.intp],
    intrinsics: Intrinsics,
) -> list[tuple[PoseFit, NDArray[np.intp], NDArray[np.intp]]]:
    """Edge fits of the ``usable`` detections (one or two) from the start views, over their
    assignments: each fit with its detections and objects."""
    candidates = [np.flatnonzero(compatible[i]).tolist() for i in usable]
    assignments = [a for a in itertools.product(*candidates) if len(set(a)) == len(a)]
    fits = []
    for objs in assignments[:MAX_FEW_ASSIGNMENTS]:
        paired = objects.subset(objs)
        target = paired.centroids.mean(axis=0)
        for theta, phi in FEW_STARTS_DEG:
            rvec, tvec = start_view(theta, phi, objects.radius, target)
            fit = refine_edges(paired, boxes[usable], masks[usable], rvec, tvec, intrinsics)
            if fit.position()[2] > 0.0:
                fits.append((fit, usable, np.asarray(objs, dtype=np.intp)))
    return fits


def few_detections(compatible: NDArray[np.bool_], order: NDArray[np.intp]) -> NDArray[np.intp]:
    """Up to two detections, most confident first, that distinct objects can be: with no pose
    hypothesis, more would only repeat objects (six boxes labelled ``mesh`` in a scene of two
    meshes)."""
    kept: list[int] = []
    for i in order.tolist():
        trial = [*kept, i]
        rows = [np.flatnonzero(compatible[j]).tolist() for j in trial]
        if any(len(set(a)) == len(a) for a in itertools.product(*rows)):
            kept = trial
        if len(kept) == 2:
            break
    return np.asarray(kept, dtype=np.intp)
