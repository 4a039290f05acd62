"""Free targets: cameras drawn as drones take photos (issue 23, item 5), rendered with their
ground truth.

A camera of target ``i`` is drawn from a :class:`numpy.random.Generator` seeded with the bench's
seed and ``i``, after a plan seeded with the seed and the count (which targets are nadir, which
give no intrinsics, the elevation slices), so each target of a draw is reproducible on its own:

* the point it looks at: uniform on the objects' footprint's bounding rectangle, grown by
  :data:`AREA_MARGIN` of the scene radius r on each side, on the ground (z = 0);
* its distance from that point: uniform in [0.4 r, 1.6 r];
* its elevation ε above the ground plane, seen from that point: a :data:`NADIR_SHARE` of the
  targets (chosen by a seeded permutation) look straight down (ε = 90°, pitch 90°), the others
  take ε in [10°, 89°], stratified (:func:`elevation_strata`): the ``m`` of them that give their
  intrinsics take one of ``m`` equal slices of the range each, in a seeded order, and ε uniform
  within it, and so do those that do not. Each ε is still uniform over the range, and a draw
  of 8 targets spans it: drawn independently, seed 1's 24 targets of ``cosmos bench --free
  --random-scenes 2 --n 8`` held no camera between 60° and 89°, and the 9 without intrinsics
  none above 60°, where distance trades against focal length. The camera looks at the point,
  so its pitch is ε;
* its azimuth uniform in [0°, 360°), its roll uniform in ±25° (``roll_limit`` widens it: a
  photo held upright is rolled 90°);
* its horizontal fov uniform within ±30 % of the scene camera's (:data:`FOV_RANGE`; a drone's
  lens may lie farther from the scene file's camera: ``fov_range`` widens it); a third of the
  targets (again a seeded permutation) are flagged as not giving their intrinsics.

The elevation and the fov are drawn once per target. A camera that stands below the ground or
inside an object's bounding box, or that does not see at least :data:`MIN_OBJECTS` objects at
least :data:`MIN_VISIBLE` visible (the renderer's ``visible_fraction`` times the share the frame
does not cut off: :func:`visible_shares`), is drawn again at that elevation and fov, up to
``max_tries`` times per target.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import Final, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from cosmos.bench.free_targets.estimate import intrinsics_matrix
from cosmos.bench.free_targets.rendering import Renderer
from cosmos.bench.free_targets.shapes import SceneShapes, project_boxes
from cosmos.bench.variants import degrade
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.errors import UnprocessableError
from services.common.geometry.free_camera import (
    FreeCamera,
    free_pinhole_camera,
    orbit_position,
)
from services.common.geometry.scene import LoadedScene
from services.renderer.client import RendererError

__all__ = [
    "BANDS",
    "DISTANCE_RANGE",
    "ELEVATION_RANGE_DEG",
    "FOV_RANGE",
    "FOV_SPREAD",
    "FREE_VARIANTS",
    "MAX_FOV_DEG",
    "MIN_OBJECTS",
    "MIN_VISIBLE",
    "NADIR_SHARE",
    "ROLL_LIMIT_DEG",
    "Band",
    "DrawError",
    "DrawnCamera",
    "FreeTarget",
    "FreeVariant",
    "band_of",
    "draw_camera",
    "draw_elevation_fov",
    "draw_targets",
    "elevation_strata",
    "target_film",
    "usable_objects",
    "visible_shares",
]

DISTANCE_RANGE: Final = (0.4, 1.6)
"""Distance from the looked-at point, in scene radii."""
ELEVATION_RANGE_DEG: Final = (10.0, 89.0)
"""Elevation of the cameras that are not nadir."""
NADIR_SHARE: Final = 0.15
ROLL_LIMIT_DEG: Final = 25.0
FOV_SPREAD: Final = 0.30
"""The fov lies within ±this fraction of the scene camera's."""
FOV_RANGE: Final = (1.0 - FOV_SPREAD, 1.0 + FOV_SPREAD)
"""The fov's range as factors of the scene camera's (issue 23's ±30 %)."""
MAX_FOV_DEG: Final = 170.0
"""No target's fov reaches this (a pinhole's fov stays below 180°)."""
NOT_GIVEN_SHARE: Final = 1.0 / 3.0
"""The share of targets that do not give their intrinsics."""
AREA_MARGIN: Final = 0.05
"""The object area's rectangle is grown by this fraction of the radius on each side."""
MIN_OBJECTS: Final = 3
MIN_VISIBLE: Final = 0.6
MAX_TRIES: Final = 60
FloatArray = NDArray[np.float64]

Band = Literal["10-30", "30-60", "60-89", "nadir"]
BANDS: Final[tuple[Band, ...]] = get_args(Band)

FreeVariant = Literal["clean", "jpeg", "noise"]
FREE_VARIANTS: Final[tuple[FreeVariant, ...]] = get_args(FreeVariant)
"""The degradations of :func:`cosmos.bench.variants.degrade` that apply to any image."""


class DrawError(ValueError):
    """A scene where no camera drawn within the tries sees enough objects."""


def band_of(elevation_deg: float) -> Band:
    """The elevation band: 10–30°, 30–60°, 60–89° (up to but not at 90°), or nadir (90°)."""
    if elevation_deg >= 90.0:
        return "nadir"
    if elevation_deg >= 60.0:
        return "60-89"
    return "30-60" if elevation_deg >= 30.0 else "10-30"


@dataclass(frozen=True)
class DrawnCamera:
    """One drawn camera, before any render: the camera and how it was drawn."""

    camera: FreeCamera
    """Position, yaw/pitch/roll and the true fov."""
    look_at: tuple[float, float, float]
    distance: float
    """From ``look_at``, scene units."""
    elevation_deg: float


@dataclass(frozen=True)
class FreeTarget:
    """A free target: its image and everything true about it."""

    scene: str
    index: int
    drawn: DrawnCamera
    intrinsics_given: bool
    """Whether a search is told the camera's intrinsics (else it must estimate the fov)."""
    annotations: RenderAnnotations
    """The renderer's ground truth: exact boxes, visible fractions, the pinhole camera."""
    usable: tuple[str, ...]
    """The objects at least :data:`MIN_VISIBLE` visible (:func:`usable_objects`)."""
    png: bytes = field(repr=False)
    """The clean image as the renderer delivers it."""

    @property
    def camera(self) -> FreeCamera:
        return self.drawn.camera

    @property
    def band(self) -> Band:
        return band_of(self.drawn.elevation_deg)

    def image(self, variant: FreeVariant, rng: np.random.Generator) -> bytes:
        """The target image of ``variant`` (:func:`cosmos.bench.variants.degrade`)."""
        return degrade(self.png, variant, rng)


def visible_shares(annotations: RenderAnnotations, shapes: SceneShapes) -> dict[str, float]:
    """How much of each object a pinhole view shows, in [0, 1]: the renderer's
    ``visible_fraction`` (what is not hidden behind other objects, counted inside the frame only)
    times the share of the object's projected bounding box that lies inside the frame (what the
    frame does not cut off; the box's area stands for the silhouette's)."""
    camera = annotations.camera
    rotation, translation = np.asarray(camera.rotation), np.asarray(camera.translation)
    boxes = project_boxes(shapes, rotation, translation, intrinsics_matrix(camera))
    film = np.array([camera.width, camera.height] * 2, dtype=np.float64)
    clipped = np.clip(boxes, 0.0, film)

    def area(b: FloatArray) -> FloatArray:
        result: FloatArray = np.maximum(b[:, 2] - b[:, 0], 0.0) * np.maximum(b[:, 3] - b[:, 1], 0.0)
        return result

    full = area(boxes)
    in_frame = np.divide(area(clipped), full, out=np.zeros_like(full), where=full > 0)
    shares = {}
    for obj in annotations.objects:
        i = shapes.names.index(obj.name)
        shares[obj.name] = float(obj.visible_fraction * in_frame[i]) if obj.box is not None else 0.0
    return shares


def usable_objects(
    annotations: RenderAnnotations, shapes: SceneShapes, min_visible: float = MIN_VISIBLE
) -> tuple[str, ...]:
    """Names of the objects at least ``min_visible`` visible (:func:`visible_shares`), in the
    scene's order: the objects a target is drawn to show, and the ones the references use."""
    shares = visible_shares(annotations, shapes)
    return tuple(obj.name for obj in annotations.objects if shares[obj.name] >= min_visible)


def _object_area(scene: LoadedScene, shapes: SceneShapes) -> tuple[float, float, float, float]:
    margin = AREA_MARGIN * scene.spec.camera.radius
    x0, y0 = shapes.lo[:, :2].min(axis=0) - margin
    x1, y1 = shapes.hi[:, :2].max(axis=0) + margin
    return float(x0), float(y0), float(x1), float(y1)


def elevation_strata(
    nadir: NDArray[np.bool_], not_given: NDArray[np.bool_], rng: np.random.Generator
) -> list[tuple[int, int] | None]:
    """Each target's elevation slice ``(j, m)``: slice ``j`` of ``m`` equal ones of
    :data:`ELEVATION_RANGE_DEG`, where ``m`` counts the targets that are not nadir and give their
    intrinsics as this one does (or do not), and their ``j`` are a seeded permutation; None for
    a nadir target."""
    strata: list[tuple[int, int] | None] = [None] * len(nadir)
    for group in (False, True):
        members = np.flatnonzero(~nadir & (not_given == group))
        for j, index in zip(rng.permutation(len(members)), members, strict=True):
            strata[int(index)] = (int(j), len(members))
    return strata


def draw_elevation_fov(
    scene: LoadedScene,
    stratum: tuple[int, int] | None,
    rng: np.random.Generator,
    fov_range: tuple[float, float] = FOV_RANGE,
) -> tuple[float, float]:
    """A target's elevation and fov in degrees (module docstring): the elevation uniform within
    slice ``j`` of ``m`` of :data:`ELEVATION_RANGE_DEG` for ``stratum`` ``(j, m)``, 90° for
    None (nadir); the fov uniform within ``fov_range`` times the scene camera's. Drawn once per
    target, so that the cameras redrawn for visibility keep their distribution."""
    if stratum is None:
        elevation = 90.0
    else:
        j, m = stratum
        lo, hi = ELEVATION_RANGE_DEG
        elevation = lo + (j + float(rng.uniform())) * (hi - lo) / m
    fov = scene.spec.camera.fov_deg * float(rng.uniform(*fov_range))
    return elevation, fov


def draw_camera(
    scene: LoadedScene,
    shapes: SceneShapes,
    elevation: float,
    fov: float,
    rng: np.random.Generator,
    roll_limit: float = ROLL_LIMIT_DEG,
) -> DrawnCamera:
    """One camera at ``elevation`` with ``fov`` (degrees), the rest drawn as the module
    docstring says: the looked-at point, the distance, the azimuth and the roll (within
    ``±roll_limit``)."""
    x0, y0, x1, y1 = _object_area(scene, shapes)
    look = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)), 0.0)
    distance = float(rng.uniform(*DISTANCE_RANGE)) * scene.spec.camera.radius
    azimuth = float(rng.uniform(0.0, 360.0))
    roll = float(rng.uniform(-roll_limit, roll_limit))
    position = orbit_position(look, distance, elevation, azimuth)
    camera = FreeCamera(
        position=position,
        yaw_deg=(azimuth + 180.0) % 360.0,  # looking back at the point
        pitch_deg=elevation,
        roll_deg=roll,
        fov_deg=fov,
    )
    return DrawnCamera(camera=camera, look_at=look, distance=distance, elevation_deg=elevation)


def _placeable(drawn: DrawnCamera, shapes: SceneShapes) -> bool:
    """Above the ground and outside every object's bounding box."""
    position = np.asarray(drawn.camera.position)
    inside = np.all((position > shapes.lo) & (position < shapes.hi), axis=1)
    return bool(position[2] > 0.0 and not inside.any())


def _may_see_enough(
    drawn: DrawnCamera, shapes: SceneShapes, width: int, height: int, fov_deg: float
) -> bool:
    """Whether at least :data:`MIN_OBJECTS` centroids project into the image in front of the
    camera: a cheap test before the render that decides."""
    camera = free_pinhole_camera(drawn.camera, width, height, fov_deg)
    cam = shapes.centroids @ np.asarray(camera.rotation).T + np.asarray(camera.translation)
    depth = cam[:, 2]
    ahead = depth > 1e-6
    u = camera.fx * cam[:, 0] / np.where(ahead, depth, 1.0) + camera.cx
    v = camera.fy * cam[:, 1] / np.where(ahead, depth, 1.0) + camera.cy
    inside = ahead & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    return int(inside.sum()) >= MIN_OBJECTS


def _shares(count: int, share: float, rng: np.random.Generator) -> np.ndarray:
    """A boolean mask with ``round(share · count)`` True, at seeded random places."""
    mask = np.zeros(count, dtype=bool)
    mask[rng.permutation(count)[: round(share * count)]] = True
    return mask


def target_film(
    width: int | None, aspect: tuple[int, int] | None, scene_width: int
) -> tuple[int | None, int | None]:
    """The targets' film ``(width, height)`` for ``--target-width`` ``width`` (else the scene
    camera's ``scene_width``) on ``--target-aspect`` ``w:h``: ``height = round(width · h / w)``;
    None where the scene camera's own is meant."""
    if aspect is None:
        return width, None
    wide = width or scene_width
    return wide, max(1, round(wide * aspect[1] / aspect[0]))


def draw_targets(
    renderer: Renderer,
    scene: LoadedScene,
    shapes: SceneShapes,
    count: int,
    seed: int,
    *,
    width: int | None = None,
    height: int | None = None,
    spp: int = 16,
    max_tries: int = MAX_TRIES,
    only: Collection[int] | None = None,
    fov_range: tuple[float, float] = FOV_RANGE,
    roll_limit: float = ROLL_LIMIT_DEG,
) -> list[FreeTarget]:
    """``count`` free targets of ``scene`` (module docstring), rendered by ``renderer`` on a
    ``width`` x ``height`` film (the scene camera's by default) at ``spp`` samples, their fov
    within ``fov_range`` times the scene camera's, their roll within ``±roll_limit`` degrees;
    with ``only``, just the targets of those indices (each is the same as in the whole draw).
    Another ``roll_limit`` draws the same cameras rolled more or less, unless one then sees too
    little and is drawn again.

    Raises
    ------
    DrawError
        No camera of ``max_tries`` drawn for one target saw :data:`MIN_OBJECTS` objects at least
        :data:`MIN_VISIBLE` visible; or ``fov_range`` reaches :data:`MAX_FOV_DEG` on this scene.
    """
    spec = scene.spec.camera
    low, high = fov_range
    if not 0.0 < low <= high or spec.fov_deg * high >= MAX_FOV_DEG:
        raise DrawError(
            f"a fov range of {low:g}-{high:g} times {scene.id}'s {spec.fov_deg:g}° leaves "
            f"(0°, {MAX_FOV_DEG:g}°)"
        )
    width = width or spec.width
    height = height or round(width * spec.height / spec.width)
    plan = np.random.default_rng([seed, count])
    nadir = _shares(count, NADIR_SHARE, plan)
    not_given = _shares(count, NOT_GIVEN_SHARE, plan)
    strata = elevation_strata(nadir, not_given, plan)
    targets = []
    for index in range(count):
        if only is not None and index not in only:
            continue
        rng = np.random.default_rng([seed, index])
        elevation, fov = draw_elevation_fov(scene, strata[index], rng, fov_range)
        for _ in range(max_tries):
            drawn = draw_camera(scene, shapes, elevation, fov, rng, roll_limit)
            if not _placeable(drawn, shapes):
                continue
            if not _may_see_enough(drawn, shapes, width, height, spec.fov_deg):
                continue
            request = RenderRequest(
                scene=scene.id, camera=drawn.camera, width=width, height=height, spp=spp, seed=index
            )
            try:
                annotations = renderer.annotations(request)
            except (UnprocessableError, RendererError) as exc:
                if getattr(exc, "status", 422) != 422:
                    raise
                continue  # the renderer's own placement test is the last word
            usable = usable_objects(annotations, shapes)
            if len(usable) < MIN_OBJECTS:
                continue
            png = renderer.render_png(request)
            targets.append(
                FreeTarget(
                    scene=scene.id,
                    index=index,
                    drawn=drawn,
                    intrinsics_given=not bool(not_given[index]),
                    annotations=annotations,
                    usable=usable,
                    png=png,
                )
            )
            break
        else:
            raise DrawError(
                f"scene {scene.id}: none of {max_tries} cameras drawn for target {index} sees "
                f"{MIN_OBJECTS} objects at least {MIN_VISIBLE:.0%} visible; the scene may have "
                "too few objects, or objects too small to see from 0.4–1.6 × its radius"
            )
    return targets


def bands_of(targets: Sequence[FreeTarget]) -> dict[Band, int]:
    """How many targets each elevation band holds."""
    return {band: sum(t.band == band for t in targets) for band in BANDS}
