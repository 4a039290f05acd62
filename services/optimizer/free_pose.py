"""``POST /free-pose`` as a plain function: a request checked, solved from its boxes
(:func:`~services.optimizer.free.solve_free_pose`) and answered in the contract's terms.

What a request can get wrong that its schema cannot say is refused with a 422 naming the field:
a scene that does not exist (404), a box outside the target image, intrinsics whose field of
view reaches 180°, a lens whose distortion folds the image.

Lens distortion: the solver is a pinhole one, so a distorted target's boxes are undistorted
first: :data:`EDGE_SAMPLES` points along each side of a box are undistorted
(:func:`~services.common.geometry.lens.undistort_pixels`) and the box of their pinhole pixels
``(fx x + cx, fy y + cy)`` is the box the solver sees; a side on the image border stays on it
(it is masked: it says only that the object goes on). The predicted boxes are distorted back the
same way. A box's side is curved by the lens; its extreme is sampled to within the spacing.

Confidence of a pose: ``c = (n_paired / n_usable) · exp(−½ (r / (3 σ))²)`` with ``r`` its edge
RMS residual and ``σ`` = :data:`~services.optimizer.free.tolerances.NOISE_FLOOR_PX` (the
detector's box-edge noise) in the target's pixels (times
:func:`~services.optimizer.free.tolerances.pixel_scale`: the request's ``detector_input``
shrank the image), halved when the answer is ``ambiguous``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Final

import numpy as np

from services.common.caches import SharedLru
from services.common.catalog import SceneCatalog
from services.common.contracts.detect import Detection
from services.common.contracts.free import (
    FreeCorrespondence,
    FreePose,
    FreePoseRequest,
    FreePoseResponse,
    IntrinsicsUsed,
    PhotoIntrinsics,
    nearest_grid_pose,
)
from services.common.errors import UnprocessableError
from services.common.geometry.camera import PinholeCamera, fov_deg_of
from services.common.geometry.free_camera import LensDistortion
from services.common.geometry.lens import distort, image_folds, undistort_pixels
from services.common.geometry.scene import LoadedScene
from services.optimizer.free import (
    FreePoseAnswer,
    Intrinsics,
    PoseCandidate,
    SceneObjects,
    project_boxes,
    scene_objects,
    solve_free_pose,
)
from services.optimizer.free.tolerances import NOISE_FLOOR_PX, pixel_scale
from services.optimizer.geometry import FloatArray
from services.optimizer.planning import check_box

__all__ = ["EDGE_SAMPLES", "SceneObjectCache", "free_pose", "predicted_boxes"]

EDGE_SAMPLES: Final = 16
"""Points per box side undistorted (or distorted) to map a box through the lens."""
MAX_FOV_DEG: Final = 179.0
_BORDER_PX: Final = 1e-6


class SceneObjectCache:
    """Each scene's objects as the solver sees them (:func:`scene_objects`: meshes read, hulls
    taken), built once per scene file version and kept in a :class:`SharedLru`."""

    def __init__(self, max_scenes: int = 16) -> None:
        self._lru = SharedLru[SceneObjects](max_scenes)

    @property
    def hits(self) -> int:
        return self._lru.hits

    def get(self, scene: LoadedScene) -> SceneObjects:
        """The objects of ``scene`` (built on a miss)."""
        return self._lru.get(
            (scene.id, scene.path, scene.version), lambda: scene_objects(scene.spec, scene.assets)
        )


def _invalid(detail: str, field: str, slug: str = "invalid-request") -> UnprocessableError:
    return UnprocessableError(detail, field=field, slug=slug)


def _pinhole(intrinsics: Intrinsics, width: int, height: int) -> PinholeCamera:
    """A pinhole of these intrinsics at the origin (the lens functions want one)."""
    return PinholeCamera(
        width=width,
        height=height,
        fov_deg=intrinsics.fov_deg(width),
        fx=intrinsics.fx,
        fy=intrinsics.fy,
        cx=intrinsics.cx,
        cy=intrinsics.cy,
        rotation=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        translation=(0.0, 0.0, 0.0),
        position=(0.0, 0.0, 0.0),
    )


def _given(
    photo: PhotoIntrinsics, width: int, height: int
) -> tuple[Intrinsics, LensDistortion | None]:
    """The request's intrinsics in target pixels, checked; the lens (None without distortion)."""
    if photo.fx_px is not None and photo.fy_px is not None:
        cx = photo.cx_px if photo.cx_px is not None else width / 2.0
        cy = photo.cy_px if photo.cy_px is not None else height / 2.0
        k = Intrinsics(fx=photo.fx_px, fy=photo.fy_px, cx=cx, cy=cy)
    else:
        k = Intrinsics.of_fov(photo.fov_deg or 0.0, width, height)
    for name, side, focal in (("fx_px", width, k.fx), ("fy_px", height, k.fy)):
        if not fov_deg_of(focal, side) < MAX_FOV_DEG:
            raise _invalid(
                f"{name} {focal:g} gives a field of view of 180° or more over {side} pixels",
                f"intrinsics.{name}",
                "field-of-view-too-wide",
            )
    lens = photo.distortion
    if lens is None or lens.is_zero:
        return k, None
    if image_folds(_pinhole(k, width, height), lens):
        raise _invalid(
            "the radial distortion (k1, k2, k3) stops increasing before the image's corners, so it "
            "folds the image: dr_d/dr = 1 + 3 k1 r² + 5 k2 r⁴ must stay positive",
            "intrinsics.distortion.k1",
            "distortion-folds-image",
        )
    return k, lens


def _edge_points(boxes: FloatArray) -> FloatArray:
    """``(n, 4·S, 2)`` points along the sides of ``(n, 4)`` boxes, S = :data:`EDGE_SAMPLES`."""
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES)
    x1, y1, x2, y2 = (boxes[:, i, np.newaxis] for i in range(4))
    xs = x1 + (x2 - x1) * s
    ys = y1 + (y2 - y1) * s
    ones = np.ones_like(s)
    u = np.concatenate([xs, xs, x1 * ones, x2 * ones], axis=1)
    v = np.concatenate([y1 * ones, y2 * ones, ys, ys], axis=1)
    return np.stack([u, v], axis=-1)


def _bounds(points: FloatArray) -> FloatArray:
    return np.concatenate([points.min(axis=1), points.max(axis=1)], axis=1)


def _undistorted(
    detections: tuple[Detection, ...], k: Intrinsics, lens: LensDistortion, size: tuple[int, int]
) -> tuple[Detection, ...]:
    """The detections with their boxes in the pinhole image of the same intrinsics (module
    docstring); sides on the border stay there."""
    width, height = size
    boxes = np.array([d.box for d in detections], dtype=np.float64).reshape(-1, 4)
    try:
        xy = undistort_pixels(_edge_points(boxes), _pinhole(k, width, height), lens)
    except ValueError as exc:
        raise _invalid(str(exc), "intrinsics.distortion", "distortion-folds-image") from exc
    pixels = np.stack([k.fx * xy[..., 0] + k.cx, k.fy * xy[..., 1] + k.cy], axis=-1)
    out = _bounds(pixels)
    border = np.array([0.0, 0.0, width, height])
    on_border = np.isclose(boxes, border, atol=_BORDER_PX)
    out = np.where(on_border, border, out)
    return tuple(
        d.model_copy(update={"box": tuple(float(v) for v in row)})
        for d, row in zip(detections, out, strict=True)
    )


def predicted_boxes(
    objects: SceneObjects,
    names: list[str],
    camera_to_world: FloatArray,
    position: tuple[float, float, float],
    intrinsics: tuple[float, float, float, float],
    lens: LensDistortion | None,
) -> dict[str, tuple[float, float, float, float] | None]:
    """The boxes of the objects ``names`` projected by the camera at ``position`` turned by
    ``camera_to_world``, of pixel ``intrinsics`` ``(fx, fy, cx, cy)`` (through the ``lens``),
    by object name; None for one that does not project (behind the camera)."""
    fx, fy, cx, cy = intrinsics
    subset = objects.subset([objects.names.index(n) for n in names])
    rotation = np.asarray(camera_to_world, dtype=np.float64).T
    translation = -rotation @ np.asarray(position)
    boxes = project_boxes(subset, rotation, translation, (fx, fy), (cx, cy))
    if lens is not None and np.isfinite(boxes).all():
        points = _edge_points(boxes)
        xy = np.stack([(points[..., 0] - cx) / fx, (points[..., 1] - cy) / fy], -1)
        d = distort(xy, lens)
        boxes = _bounds(np.stack([fx * d[..., 0] + cx, fy * d[..., 1] + cy], -1))
    return {
        name: (tuple(float(v) for v in box) if np.isfinite(box).all() else None)  # type: ignore[misc]
        for name, box in zip(names, boxes, strict=True)
    }


def _predicted(
    objects: SceneObjects, pose: PoseCandidate, lens: LensDistortion | None
) -> dict[str, tuple[float, float, float, float] | None]:
    """Each paired object's box projected at ``pose`` (through the lens), by object name."""
    k = pose.intrinsics
    names = [c.object for c in pose.correspondences]
    focal = (k.fx_px, k.fy_px, k.cx_px, k.cy_px)
    return predicted_boxes(objects, names, pose.rotation(), pose.position, focal, lens)


def _sigma(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _pose(
    candidate: PoseCandidate,
    objects: SceneObjects,
    lens: LensDistortion | None,
    evidence: tuple[int, float],
    ambiguous: bool,
) -> FreePose:
    """``candidate`` in the contract's terms; ``evidence`` is the usable detections and the
    target pixels per pixel of the detector's input."""
    usable, scale = evidence
    k = candidate.intrinsics
    predicted = _predicted(objects, candidate, lens)
    fit = math.exp(-0.5 * (candidate.residual_px / (3.0 * NOISE_FLOOR_PX * scale)) ** 2)
    confidence = min(1.0, candidate.inliers / max(usable, 1)) * fit * (0.5 if ambiguous else 1.0)
    return FreePose(
        position=candidate.position,
        quaternion_wxyz=candidate.quaternion_wxyz,
        yaw_pitch_roll_deg=candidate.yaw_pitch_roll_deg,
        intrinsics=IntrinsicsUsed(
            fx_px=k.fx_px,
            fy_px=k.fy_px,
            cx_px=k.cx_px,
            cy_px=k.cy_px,
            fov_deg=k.fov_deg,
            source=k.source,
            distortion=lens,
        ),
        correspondences=tuple(
            FreeCorrespondence(
                detection=c.detection,
                object=c.object,
                label=c.label,
                residual_px=c.residual_px,
                predicted_box=predicted[c.object],
            )
            for c in candidate.correspondences
        ),
        residual_px=candidate.residual_px,
        confidence=confidence,
        position_sigma=_sigma(candidate.position_sigma),
        rotation_sigma_deg=_sigma(candidate.rotation_sigma_deg),
    )


def free_pose(
    request: FreePoseRequest, catalog: SceneCatalog | None, cache: SceneObjectCache
) -> FreePoseResponse:
    """The camera pose of the request's target from its boxes alone (module docstring)."""
    if catalog is None:
        raise _invalid("this optimizer has no scene catalog", "scene")
    scene = catalog.get(request.scene)  # NotFoundError (404) names the field
    width, height = request.target.image_size
    detections = request.target.detections
    for i, detection in enumerate(detections):
        check_box(detection, width, height, f"target.detections[{i}].box")
    k: Intrinsics | None = None
    lens = None
    if request.intrinsics is not None:
        k, lens = _given(request.intrinsics, width, height)
        if lens is not None and detections:
            detections = _undistorted(detections, k, lens, (width, height))
    objects = cache.get(scene)
    scale = pixel_scale((width, height), request.detector_input)
    known_from = request.intrinsics.source if request.intrinsics is not None else "given"
    stated = request.attitude
    solved = solve_free_pose(
        objects,
        detections,
        width,
        height,
        k,
        pixel_scale=scale,
        known_from=known_from,
        attitude=None if stated is None else (stated.pitch_deg, stated.roll_deg),
    )
    answer = _renderable(solved, objects)
    grid = scene.spec.search.grid()
    ambiguous = answer.status == "ambiguous"
    usable = answer.usable_detections

    def pose(candidate: PoseCandidate) -> FreePose:
        return _pose(candidate, objects, lens, (usable, scale), ambiguous)

    best = answer.pose
    return FreePoseResponse(
        status=answer.status,
        reason=answer.reason,
        pose=pose(best) if best is not None else None,
        alternatives=tuple(pose(a) for a in answer.alternatives),
        nearest_grid=nearest_grid_pose(best.position, grid) if best is not None else None,
        usable_detections=usable,
        ambiguity=answer.ambiguity,
    )


def _renderable(answer: FreePoseAnswer, objects: SceneObjects) -> FreePoseAnswer:
    """``answer`` without the poses inside an object's world bounding box (the box of its
    points, as the renderer refuses such a camera): a wrong pose that no render could check.
    When the best one goes, the next alternative takes its place (``ambiguous`` still, as one of
    ``rivals``), and with none left the answer is ``failed``."""
    lo = np.minimum.reduceat(objects.points, objects.starts)
    hi = np.maximum.reduceat(objects.points, objects.starts)

    def outside(p: PoseCandidate) -> bool:
        c = np.asarray(p.position)
        return not bool(np.any(np.all((c > lo) & (c < hi), axis=1)))

    poses = [p for p in (answer.pose, *answer.alternatives) if p is not None]
    kept = [p for p in poses if outside(p)]
    if len(kept) == len(poses):
        return answer
    if not kept:
        reason = "failed: every camera pose that explains the detections stands inside an object"
        return replace(
            answer, status="failed", reason=reason, pose=None, alternatives=(), ambiguity=None
        )
    if kept[0] is answer.pose:
        return replace(answer, alternatives=tuple(kept[1:]))
    # an alternative in the best one's place: one of several the boxes allow, not the one
    return replace(answer, pose=kept[0], alternatives=tuple(kept[1:]), ambiguity="rivals")
