"""The render engine: one dedicated Mitsuba worker thread, a cache of loaded scenes, and the
products of a view: the RGB image, the per-object ground truth and the per-pixel depth.

Mitsuba is not safe across arbitrary threads, so the variant is set and every Mitsuba call runs on
a single worker thread; a process scales by running more processes. Each (scene, film size) is
loaded once; moving the camera only rewrites the sensor transform through ``mi.traverse``, so the
JIT variant reuses its compiled kernels (spp and seed are opaque too).

The worker is shared in slices (:mod:`services.renderer.scheduler`): a render of more than
``slice_samples`` samples runs as several sample passes over the whole film, each with its own
seed, averaged with weights by their spp (the film's box filter makes that the very estimator of
one render with all the samples); the ground truth runs one silhouette per slice. Between slices,
more urgent work (a search view) goes first. A render within one slice is one Mitsuba call, as
before, pixel for pixel.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ParamSpec, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from services.common.caches import SharedLru
from services.common.contracts.render import RenderAnnotations
from services.common.errors import ServiceUnavailableError
from services.common.geometry.camera import PinholeCamera, pinhole_camera
from services.common.geometry.lens import project_lens
from services.common.geometry.pose import GridIndex, Pose
from services.common.geometry.scene import LoadedScene
from services.renderer.annotate import object_annotations, silhouettes
from services.renderer.depth import GEOMETRY_AOVS, DepthImage, depth_image
from services.renderer.free_view import FreeView
from services.renderer.imaging import linear_to_srgb8
from services.renderer.pool import lower_worker_priority
from services.renderer.scene_builder import (
    build_object_scene,
    build_scene,
    object_index_of,
    place_sensor,
    shape_keys,
)
from services.renderer.scheduler import (
    DEFAULT_SLICE_SAMPLES,
    Job,
    Scheduler,
    pass_seed,
    sample_passes,
    single_slice,
)
from services.renderer.variant import SCALAR_VARIANT, VariantChoice, VariantRequest, choose_variant
from services.renderer.view import check_outside_objects

__all__ = ["RenderEngine", "RenderedImage"]

_log = logging.getLogger("cosmos.renderer")
FROZEN_RECORDINGS = 16  # frozen render recordings kept (scenes x film sizes x spp in use)
P = ParamSpec("P")
Key = tuple[str, int, int, int]
T = TypeVar("T")


@dataclass(frozen=True)
class RenderedImage:
    """An 8-bit sRGB ``(H, W, 3)`` render and how long the Mitsuba call took."""

    rgb: NDArray[np.uint8]
    render_ms: float


@dataclass
class _Loaded:
    """A scene loaded at one film size, with what is needed to map shapes back to objects."""

    scene: Any
    params: Any
    camera_sensor: Any
    mask_sensor: Any
    shape_to_object: NDArray[np.int64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    object_scenes: dict[int, tuple[Any, Any]] = field(default_factory=dict)


class RenderEngine:
    """Renders views of scenes on one Mitsuba worker thread.

    Sync methods (:meth:`render`, :meth:`annotate`) block the caller; the ``*_async`` variants
    await the worker without blocking an event loop. At most ``max_queue`` calls may wait or run
    at once; more raise :class:`ServiceUnavailableError`. Work is done in slices of at most
    ``slice_samples`` samples (see the module's docstring).
    """

    def __init__(
        self,
        variant: VariantRequest = "auto",
        cache_size: int = 8,
        max_queue: int = 32,
        *,
        freeze: bool = True,
        slice_samples: int = DEFAULT_SLICE_SAMPLES,
    ) -> None:
        if cache_size < 1 or max_queue < 1 or slice_samples < 1:
            raise ValueError("cache_size, max_queue and slice_samples must be at least 1")
        self._choice: VariantChoice = choose_variant(variant)
        self._max_queue = max_queue
        self._freeze = freeze
        self._slice_samples = slice_samples
        self._workers_niced = False
        self._scheduler = Scheduler(thread_name="mitsuba")
        self._lock = threading.Lock()
        self._in_flight = 0
        # Filled on the worker thread, read by loaded_scenes on the event loop: under a lock.
        self._cache = SharedLru[_Loaded](cache_size)
        self._mi: Any = None
        self._dr: Any = None
        self._aov: Any = None
        self._geometry: Any = None
        self._render_view: Callable[[Any, Any, Any, int, Key], Any] = self._traced_render
        self.variant = ""
        self.variant_reason = ""

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Set the Mitsuba variant on the worker thread (falls back to scalar if LLVM fails)."""
        self._scheduler.submit(single_slice(self._init_worker), 0).result()
        _log.info("mitsuba variant %s (%s)", self.variant, self.variant_reason)

    def close(self) -> None:
        """Finish the slice under way, cancel the rest, and stop the worker thread."""
        self._scheduler.close()
        self._cache.clear()

    def _init_worker(self) -> None:
        choice = self._choice
        if choice.libllvm is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = choice.libllvm
        import drjit as dr
        import mitsuba as mi

        try:
            mi.set_variant(choice.variant)
        except (ImportError, AttributeError, RuntimeError) as exc:
            _log.warning("variant %s failed (%s); using %s", choice.variant, exc, SCALAR_VARIANT)
            choice = VariantChoice(SCALAR_VARIANT, None, f"{choice.variant} failed: {exc}")
            mi.set_variant(SCALAR_VARIANT)
        self._mi, self._dr = mi, dr
        self._aov = mi.load_dict({"type": "aov", "aovs": "si:shape_index"})
        self._geometry = mi.load_dict({"type": "aov", "aovs": GEOMETRY_AOVS})
        if self._freeze and choice.variant != SCALAR_VARIANT:
            # A frozen render replays the recorded kernel launches instead of tracing the
            # integrator in Python again: ~3-5 ms less per view, identical pixels
            # (tests/renderer/test_engine.py). The camera pose and seed are inputs of the
            # recording; a scene, film size or spp not seen yet records anew (at most
            # FROZEN_RECORDINGS are kept; each lens's film is one: no warning past ten).
            render, kept = self._traced_render, FROZEN_RECORDINGS
            self._render_view = dr.freeze(render, limit=kept, warn_after=1 << 30)
        self.variant, self.variant_reason = choice.variant, choice.reason

    # -- scheduling -------------------------------------------------------------------------

    @property
    def frozen_recordings(self) -> int:
        """How many frozen render recordings exist (0 when renders are traced each time)."""
        return int(getattr(self._render_view, "n_recordings", 0))

    @property
    def in_flight(self) -> int:
        """Calls waiting for or running on the worker."""
        return self._in_flight

    def loaded_scenes(self) -> tuple[str, ...]:
        """Ids of the scenes currently loaded (any film size)."""
        keys = cast(tuple[tuple[str, int, int, int], ...], self._cache.keys())
        return tuple(sorted({key[0] for key in keys}))

    def _admit(self) -> None:
        with self._lock:
            if self._in_flight >= self._max_queue:
                raise ServiceUnavailableError(
                    f"the renderer has {self._in_flight} renders queued; try again shortly",
                    slug="renderer-busy",
                    title="Renderer busy",
                )
            self._in_flight += 1

    def _release(self) -> None:
        with self._lock:
            self._in_flight -= 1

    def call(self, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """Run ``fn`` on the Mitsuba worker thread (as one slice, before queued work) and wait
        for its result."""
        return self._run(single_slice(fn, *args, **kwargs), 0)

    async def call_async(self, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """Like :meth:`call`, awaited without blocking the event loop."""
        return await self._run_async(single_slice(fn, *args, **kwargs), 0)

    def _run(self, job: Job[T], cost: int) -> T:
        self._admit()
        try:
            return self._scheduler.submit(job, cost).result()
        finally:
            self._release()

    async def _run_async(self, job: Job[T], cost: int) -> T:
        self._admit()
        try:
            return await asyncio.wrap_future(self._scheduler.submit(job, cost))
        finally:
            self._release()

    # -- products ---------------------------------------------------------------------------
    # ``pose`` is a hemisphere pose or a free camera resolved for rendering (``FreeView``); the
    # film is ``width`` x ``height`` either way (a free camera's is its own camera's).

    def render(
        self,
        scene: LoadedScene,
        pose: Pose | FreeView,
        width: int,
        height: int,
        spp: int,
        seed: int = 0,
    ) -> RenderedImage:
        """Render ``scene`` from ``pose`` (blocking)."""
        view = self.free_view(scene, pose, width, height)
        job = self._render(scene, view, spp, seed)
        return self._run(job, view.rendered.width * view.rendered.height * spp)

    async def render_async(
        self,
        scene: LoadedScene,
        pose: Pose | FreeView,
        width: int,
        height: int,
        spp: int,
        seed: int = 0,
    ) -> RenderedImage:
        """Render ``scene`` from ``pose`` on the worker."""
        view = self.free_view(scene, pose, width, height)
        job = self._render(scene, view, spp, seed)
        return await self._run_async(job, view.rendered.width * view.rendered.height * spp)

    def annotate(
        self,
        scene: LoadedScene,
        pose: Pose | FreeView,
        width: int,
        height: int,
        grid_index: GridIndex | None,
    ) -> RenderAnnotations:
        """Ground truth of the view (blocking)."""
        view = self.free_view(scene, pose, width, height)
        job = self._annotate(scene, pose, view, grid_index)
        return self._run(job, self._annotation_cost(scene, view))

    async def annotate_async(
        self,
        scene: LoadedScene,
        pose: Pose | FreeView,
        width: int,
        height: int,
        grid_index: GridIndex | None,
    ) -> RenderAnnotations:
        """Ground truth of the view on the worker."""
        view = self.free_view(scene, pose, width, height)
        job = self._annotate(scene, pose, view, grid_index)
        return await self._run_async(job, self._annotation_cost(scene, view))

    def object_map(
        self, scene: LoadedScene, pose: Pose | FreeView, width: int, height: int
    ) -> NDArray[np.int64]:
        """Per-pixel index of the object seen through each pixel centre, -1 where none."""
        view = self.free_view(scene, pose, width, height)
        job = single_slice(self._object_map, scene, view)
        return self._run(job, view.rendered.width * view.rendered.height)

    def depth(
        self, scene: LoadedScene, pose: Pose | FreeView, width: int, height: int
    ) -> DepthImage:
        """Per-pixel depth and object ids of the view (blocking; :mod:`.depth`)."""
        view = self.free_view(scene, pose, width, height)
        job = single_slice(self._depth, scene, view)
        return self._run(job, view.rendered.width * view.rendered.height)

    async def depth_async(
        self, scene: LoadedScene, pose: Pose | FreeView, width: int, height: int
    ) -> DepthImage:
        """Per-pixel depth and object ids of the view on the worker."""
        view = self.free_view(scene, pose, width, height)
        job = single_slice(self._depth, scene, view)
        return await self._run_async(job, view.rendered.width * view.rendered.height)

    @staticmethod
    def free_view(scene: LoadedScene, pose: Pose | FreeView, width: int, height: int) -> FreeView:
        """The camera of a view as a :class:`FreeView` (a hemisphere pose renders directly)."""
        if isinstance(pose, FreeView):
            return pose
        spec = scene.spec.camera
        camera = pinhole_camera(pose, spec.radius, spec.fov_deg, width, height)
        return FreeView(camera=camera, distortion=None, rendered=camera)

    @staticmethod
    def _annotation_cost(scene: LoadedScene, view: FreeView) -> int:
        return view.rendered.width * view.rendered.height * (len(scene.spec.objects) + 1)

    # -- worker-side ------------------------------------------------------------------------

    def loaded(self, scene: LoadedScene, width: int, height: int) -> _Loaded:
        """The scene loaded at this film size, from the cache or loaded now (worker thread only)."""
        key = (scene.id, scene.version, width, height)
        return self._cache.get(key, lambda: self._load(scene, width, height))

    def _load(self, scene: LoadedScene, width: int, height: int) -> _Loaded:
        """Load the scene at this film size (worker thread only)."""
        mi = self._mi
        started = time.perf_counter()
        # optimize=False: Mitsuba would otherwise merge meshes that share a material into one
        # shape, and their objects could no longer be told apart in the shape-id image.
        mi_scene = mi.load_dict(build_scene(mi, scene, width, height), optimize=False)
        shapes = list(mi_scene.shapes())
        keys = shape_keys(self._mi, self._dr, self.variant, shapes)
        count = len(scene.spec.objects)
        shape_to_object = np.full(max(keys) + 1, -1, dtype=np.int64)
        lo = np.full((count, 3), np.inf)
        hi = np.full((count, 3), -np.inf)
        for shape_key, shape in zip(keys, shapes, strict=True):
            index = object_index_of(shape.id())
            shape_to_object[shape_key] = index
            if index >= 0:
                box = shape.bbox()
                lo[index] = np.minimum(lo[index], np.array(box.min, dtype=np.float64).ravel())
                hi[index] = np.maximum(hi[index], np.array(box.max, dtype=np.float64).ravel())
        unmapped = [
            scene.spec.objects[i].name for i in range(count) if not np.isfinite(lo[i]).all()
        ]
        if unmapped:
            raise RuntimeError(f"scene {scene.id}: no Mitsuba shape for objects {unmapped}")
        sensors = {sensor.id(): sensor for sensor in mi_scene.sensors()}
        loaded = _Loaded(
            scene=mi_scene,
            params=mi.traverse(mi_scene),
            camera_sensor=sensors["camera"],
            mask_sensor=sensors["mask_camera"],
            shape_to_object=shape_to_object,
            lo=lo,
            hi=hi,
        )
        _log.info(
            "loaded scene %s at %dx%d in %.0f ms",
            scene.id,
            width,
            height,
            (time.perf_counter() - started) * 1000,
        )
        return loaded

    def _place(self, params: Any, sensor: str, camera: PinholeCamera) -> None:
        place_sensor(self._mi, params, sensor, camera)

    def _check_placement(self, loaded: _Loaded, pose: Pose | FreeView) -> None:
        if isinstance(pose, FreeView):
            check_outside_objects(pose.camera.position, loaded.lo, loaded.hi)

    def _traced_render(self, scene: Any, sensor: Any, seed: Any, spp: int, key: Key) -> Any:
        """A render by ``sensor``; ``key`` (scene id, version, film size), unused here, joins
        the frozen recording's key, which sees only the JIT inputs' layout otherwise."""
        return self._mi.render(scene, sensor=sensor, spp=spp, seed=seed)

    def _render(
        self, scene: LoadedScene, view: FreeView, spp: int, seed: int
    ) -> Job[RenderedImage]:
        """A render in sample passes (:func:`sample_passes`), one slice each."""
        width, height = view.rendered.width, view.rendered.height
        passes = sample_passes(width * height, spp, self._slice_samples)
        total: NDArray[np.float32] | None = None
        render_ms = 0.0
        for index, pass_spp in enumerate(passes):
            yield width * height * pass_spp
            linear, ms = self._render_pass(scene, view, pass_spp, pass_seed(seed, index))
            render_ms += ms
            if len(passes) == 1:
                total = linear  # one pass: the very pixels of one render
            elif total is None:
                total = linear * np.float32(pass_spp)
            else:
                total += linear * np.float32(pass_spp)
        if total is None:  # sample_passes gives at least one pass
            raise RuntimeError("no sample pass was rendered")
        if len(passes) > 1:
            total /= np.float32(spp)
        if not self._workers_niced:  # the pool starts with the first launch
            self._workers_niced = lower_worker_priority() > 0
        return RenderedImage(rgb=linear_to_srgb8(view.warp(total)), render_ms=render_ms)

    def _render_pass(
        self, scene: LoadedScene, view: FreeView, spp: int, seed: int
    ) -> tuple[NDArray[np.float32], float]:
        """One Mitsuba render of the rendered film: linear RGB ``(h, w, 3)`` and its time in ms."""
        width, height = view.rendered.width, view.rendered.height
        loaded = self.loaded(scene, width, height)
        self._check_placement(loaded, view)
        # Placed on every pass: another job's slice may have moved this cached camera.
        self._place(loaded.params, "camera", view.rendered)
        started = time.perf_counter()
        # The seed as a JIT value, so that a new seed does not need a new recording.
        jit_seed = seed if self.variant == SCALAR_VARIANT else self._mi.UInt32(seed)
        key = (scene.id, scene.version, width, height)
        sensor = loaded.camera_sensor
        pixels = np.asarray(self._render_view(loaded.scene, sensor, jit_seed, spp, key))
        if pixels.shape[:2] != (height, width):  # another film's recording replayed: trace
            _log.warning("frozen render: %s for %dx%d, traced", pixels.shape, width, height)
            getattr(self._render_view, "clear", lambda: None)()
            pixels = np.asarray(self._traced_render(loaded.scene, sensor, jit_seed, spp, key))
        linear = pixels.astype(np.float32, copy=False).reshape(height, width, -1)[..., :3]
        return linear, (time.perf_counter() - started) * 1000.0

    def _shape_ids(self, scene: Any, sensor: Any, width: int, height: int) -> NDArray[np.int64]:
        """Per-pixel 1-based shape positions (0 = no hit), one ray through each pixel centre."""
        image = self._mi.render(scene, sensor=sensor, integrator=self._aov, spp=1)
        values = np.asarray(image, dtype=np.float32).reshape(height, width, -1)[..., -1]
        ids: NDArray[np.int64] = np.rint(values).astype(np.int64)
        return ids

    def _annotate(
        self,
        scene: LoadedScene,
        pose: Pose | FreeView,
        view: FreeView,
        grid_index: GridIndex | None,
    ) -> Job[RenderAnnotations]:
        """The ground truth in slices: the object map, then each object's own silhouette."""
        spec = scene.spec
        count = len(spec.objects)
        width, height = view.rendered.width, view.rendered.height
        yield width * height
        loaded = self.loaded(scene, width, height)
        self._check_placement(loaded, pose)
        visible = silhouettes(self._object_map(scene, view), count)
        full = silhouettes(np.full((1, 1), -1), count)  # filled object by object
        for index in range(count):
            yield width * height
            alone, params = self._object_scene(loaded, scene, index, width, height)
            self._place(params, "mask_camera", view.rendered)
            mask = self._shape_ids(alone, alone.sensors()[0], width, height) > 0
            mask = view.warp(mask.astype(np.float32), nearest=True) > 0.5
            stats = silhouettes(np.where(mask, 0, -1), 1)
            full.pixels[index], full.boxes[index] = stats.pixels[0], stats.boxes[0]
        centroids = (loaded.lo + loaded.hi) / 2.0
        projected, _ = project_lens(centroids, view.camera, view.distortion)
        objects = object_annotations(spec.objects, visible, full, centroids, projected)
        return RenderAnnotations(
            scene=scene.id,
            pose=pose if isinstance(pose, Pose) else None,
            grid_index=grid_index,
            camera=view.camera,
            distortion=view.distortion,
            objects=objects,
        )

    def _object_map(self, scene: LoadedScene, view: FreeView) -> NDArray[np.int64]:
        width, height = view.rendered.width, view.rendered.height
        loaded = self.loaded(scene, width, height)
        self._place(loaded.params, "mask_camera", view.rendered)
        ids = self._shape_ids(loaded.scene, loaded.mask_sensor, width, height)
        known = (ids >= 0) & (ids < len(loaded.shape_to_object))
        mapped = np.where(known, loaded.shape_to_object[np.where(known, ids, 0)], -1)
        warped = view.warp(mapped.astype(np.float32), nearest=True)
        result: NDArray[np.int64] = np.rint(warped).astype(np.int64)
        return result

    def _depth(self, scene: LoadedScene, view: FreeView) -> DepthImage:
        width, height = view.rendered.width, view.rendered.height
        loaded = self.loaded(scene, width, height)
        self._check_placement(loaded, view)
        self._place(loaded.params, "mask_camera", view.rendered)
        sensor, geometry = loaded.mask_sensor, self._geometry
        image = self._mi.render(loaded.scene, sensor=sensor, integrator=geometry, spp=1)
        channels = np.asarray(image, dtype=np.float32).reshape(height, width, -1)
        return depth_image(channels, loaded.shape_to_object, view)

    def _object_scene(
        self, loaded: _Loaded, scene: LoadedScene, index: int, width: int, height: int
    ) -> tuple[Any, Any]:
        """Object ``index`` alone, loaded once per cached scene, for its unoccluded silhouette."""
        if index not in loaded.object_scenes:
            data = build_object_scene(self._mi, scene, index, width, height)
            alone = self._mi.load_dict(data, optimize=False)
            loaded.object_scenes[index] = (alone, self._mi.traverse(alone))
        return loaded.object_scenes[index]
