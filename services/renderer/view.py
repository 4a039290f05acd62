"""Resolve a render request into a concrete view: the scene, the camera, the film and sampling.

Checks everything a request can get wrong against the scene and the service's caps, naming the
field: a grid index outside the scene's grid, a free camera below the ground or with a lens that
folds the image, a film (or the larger film a distorted camera is rendered on) larger than
allowed, too many samples. Whether a free camera stands inside an object's bounding box needs the
loaded scene: the engine checks it (:func:`check_outside_objects`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.errors import UnprocessableError
from services.common.geometry.camera import fov_deg_of
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera
from services.common.geometry.grid import GridError
from services.common.geometry.lens import image_folds
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.geometry.scene import LoadedScene
from services.renderer.free_view import FreeView, plan_free_view
from services.renderer.settings import RendererSettings

__all__ = ["View", "check_outside_objects", "resolve_free_camera", "resolve_pose", "resolve_view"]

_MAX_FOV_DEG = 179.0  # a pinhole's field of view only reaches 180° at a focal length of 0


@dataclass(frozen=True)
class View:
    """Everything needed to render one image."""

    scene: LoadedScene
    pose: Pose | FreeView
    """Where the camera is: a hemisphere pose, or a free camera resolved for rendering."""
    grid_index: GridIndex | None
    width: int
    height: int
    spp: int
    seed: int


def resolve_pose(scene: LoadedScene, query: PoseQuery) -> tuple[Pose, GridIndex | None]:
    """The continuous pose of ``query`` and its grid index when it is a grid pose."""
    grid = scene.spec.search.grid()
    index = query.as_index()
    if index is not None:
        if index.lat >= grid.ring_count:
            raise UnprocessableError(
                f"lat {index.lat} is outside the scene's grid (0..{grid.ring_count - 1})",
                field="pose.lat",
                slug="pose-outside-grid",
                title="Pose outside the scene's grid",
            )
        if index.lon >= grid.ring_size(index.lat):
            raise UnprocessableError(
                f"lon {index.lon} is outside ring {index.lat} (0..{grid.ring_size(index.lat) - 1})",
                field="pose.lon",
                slug="pose-outside-grid",
                title="Pose outside the scene's grid",
            )
        return grid.pose(index), index
    pose = query.as_pose()
    if pose is None:  # PoseQuery validation makes this unreachable
        raise UnprocessableError("no pose given", field="pose")
    try:
        return pose, grid.index_of(pose)
    except GridError:
        return pose, None


def _invalid_camera(detail: str, field: str, slug: str, title: str) -> UnprocessableError:
    return UnprocessableError(detail, field=f"camera.{field}", slug=slug, title=title)


def resolve_free_camera(
    scene: LoadedScene, camera: FreeCamera, width: int, height: int
) -> FreeView:
    """The free ``camera`` on a ``width`` x ``height`` film, checked against the scene's ground
    (the plane z = 0: the camera must stand above it) and for a lens that folds the image."""
    if camera.position[2] <= 0.0:
        raise _invalid_camera(
            f"the camera stands at z = {camera.position[2]:g}, not above the ground (z = 0)",
            "position",
            "camera-below-ground",
            "Camera below the ground",
        )
    pinhole = free_pinhole_camera(camera, width, height, scene.spec.camera.fov_deg)
    for name, side, focal in (("fx_px", width, pinhole.fx), ("fy_px", height, pinhole.fy)):
        if not fov_deg_of(focal, side) < _MAX_FOV_DEG:
            raise _invalid_camera(
                f"{name} {focal:g} gives a field of view of 180° or more over {side} pixels",
                name,
                "field-of-view-too-wide",
                "Field of view too wide",
            )
    distortion = camera.distortion
    if distortion is not None and image_folds(pinhole, distortion):
        raise _invalid_camera(
            "the radial distortion (k1, k2, k3) stops increasing before the film's corners, so it "
            "folds the image: dr_d/dr = 1 + 3 k1 r² + 5 k2 r⁴ must stay positive",
            "distortion.k1",
            "distortion-folds-image",
            "Distortion folds the image",
        )
    try:
        return plan_free_view(pinhole, distortion)
    except ValueError as exc:
        if distortion is None or distortion.is_zero:  # fx and fy too unequal to render
            raise _invalid_camera(str(exc), "fy_px", "film-too-large", "Film too large") from exc
        raise _invalid_camera(
            str(exc), "distortion", "distortion-folds-image", "Distortion folds the image"
        ) from exc


def check_outside_objects(
    position: tuple[float, float, float], lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> None:
    """Refuse a camera inside an object's world bounding box (``lo``, ``hi``: ``(N, 3)``)."""
    inside = np.all((np.asarray(position) > lo) & (np.asarray(position) < hi), axis=1)
    if inside.any():
        raise _invalid_camera(
            f"the camera stands inside the bounding box of object {int(np.argmax(inside))}",
            "position",
            "camera-inside-object",
            "Camera inside an object",
        )


def _film(
    scene: LoadedScene, request: RenderRequest, settings: RendererSettings
) -> tuple[int, int]:
    camera = scene.spec.camera
    aspect = camera.width / camera.height
    if request.width is None and request.height is None:
        width, height = camera.width, camera.height
    elif request.height is None:
        width = request.width or camera.width
        height = max(8, round(width / aspect))
    elif request.width is None:
        height = request.height
        width = max(8, round(height * aspect))
    else:
        width, height = request.width, request.height
    for name, value in (("width", width), ("height", height)):
        if value > settings.renderer_max_side:
            raise UnprocessableError(
                f"{name} {value} exceeds the limit of {settings.renderer_max_side} pixels",
                field=name,
                slug="film-too-large",
                title="Film too large",
            )
    if width * height > settings.renderer_max_pixels:
        raise UnprocessableError(
            f"{width}x{height} exceeds the limit of {settings.renderer_max_pixels} pixels",
            field="width",
            slug="film-too-large",
            title="Film too large",
        )
    return width, height


def resolve_view(catalog: SceneCatalog, settings: RendererSettings, request: RenderRequest) -> View:
    """Validate ``request`` against its scene and the caps of ``settings``."""
    scene = catalog.get(request.scene)
    pose: Pose | FreeView
    if request.camera is None:
        if request.pose is None:  # RenderRequest validation makes this unreachable
            raise UnprocessableError("give a pose or a camera", field="pose")
        pose, index = resolve_pose(scene, request.pose)
        width, height = _film(scene, request, settings)
        width_r, height_r = width, height  # the film Mitsuba renders
    else:
        width, height = _film(scene, request, settings)
        pose, index = resolve_free_camera(scene, request.camera, width, height), None
        if pose.rendered is not pose.camera:
            _check_rendered_film(pose, settings)
        width_r, height_r = pose.rendered.width, pose.rendered.height
    spp = request.spp if request.spp is not None else settings.renderer_default_spp
    if spp > settings.renderer_max_spp:
        raise UnprocessableError(
            f"spp {spp} exceeds the limit of {settings.renderer_max_spp}",
            field="spp",
            slug="too-many-samples",
            title="Too many samples",
        )
    if width_r * height_r * spp > settings.renderer_max_samples:
        # The cost of a render is its samples (pixels x spp); this caps one request's.
        raise UnprocessableError(
            f"{width_r}x{height_r} at {spp} spp is {width_r * height_r * spp} samples, over the "
            f"limit of {settings.renderer_max_samples} samples per render "
            "(COSMOS_RENDERER_MAX_SAMPLES)",
            field="spp",
            slug="too-many-samples",
            title="Too many samples",
            extra={"limit": settings.renderer_max_samples},
        )
    return View(scene, pose, index, width, height, spp, request.seed)


def _check_rendered_film(view: FreeView, settings: RendererSettings) -> None:
    """A distorted (or ``fx ≠ fy``) camera renders a larger pinhole film: it has the caps too."""
    width, height = view.rendered.width, view.rendered.height
    if max(width, height) > settings.renderer_max_side or width * height > (
        settings.renderer_max_pixels
    ):
        field = "distortion" if view.distortion is not None else "fy_px"
        raise _invalid_camera(
            f"this lens needs a {width}x{height} pinhole render, over the limits of "
            f"{settings.renderer_max_side} pixels a side and {settings.renderer_max_pixels} pixels",
            field,
            "film-too-large",
            "Film too large",
        )
