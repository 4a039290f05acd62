"""Resolve a render request into a concrete view: the scene, the pose, the film and sampling.

Checks everything a request can get wrong against the scene and the service's caps, naming the
field: a grid index outside the scene's grid, a film larger than allowed, too many samples.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.common.catalog import SceneCatalog
from services.common.contracts.render import RenderRequest
from services.common.errors import UnprocessableError
from services.common.geometry.grid import GridError
from services.common.geometry.pose import GridIndex, Pose, PoseQuery
from services.common.geometry.scene import LoadedScene
from services.renderer.settings import RendererSettings

__all__ = ["View", "resolve_pose", "resolve_view"]


@dataclass(frozen=True)
class View:
    """Everything needed to render one image."""

    scene: LoadedScene
    pose: Pose
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
    pose, index = resolve_pose(scene, request.pose)
    width, height = _film(scene, request, settings)
    spp = request.spp if request.spp is not None else settings.renderer_default_spp
    if spp > settings.renderer_max_spp:
        raise UnprocessableError(
            f"spp {spp} exceeds the limit of {settings.renderer_max_spp}",
            field="spp",
            slug="too-many-samples",
            title="Too many samples",
        )
    if width * height * spp > settings.renderer_max_samples:
        # The cost of a render is its samples (pixels x spp); this caps one request's.
        raise UnprocessableError(
            f"{width}x{height} at {spp} spp is {width * height * spp} samples, over the limit of "
            f"{settings.renderer_max_samples} samples per render (COSMOS_RENDERER_MAX_SAMPLES)",
            field="spp",
            slug="too-many-samples",
            title="Too many samples",
            extra={"limit": settings.renderer_max_samples},
        )
    return View(scene, pose, index, width, height, spp, request.seed)
