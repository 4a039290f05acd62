"""The floor of a search, measured in this process (``cosmos bench --profile``).

A search cannot avoid detecting its target, rendering and detecting the start view, and rendering
and detecting the final view that confirms the match (the same view when the search starts at the
target). The *floor* is the time of exactly that work, done serially in this process with the
services' own domain objects (:class:`~services.renderer.engine.RenderEngine`,
:class:`~services.detector.model.DetectorModel` with the detector's letterbox and
post-processing), warm. A rendered view is detected from its array: in one process nothing needs
a PNG.

The *one-process pipeline* replays what a real search did — the same renders (each pose once),
detections and optimizer calls (:func:`services.optimizer.planning.next_pose`), with the target's
detection overlapping the start render on a second thread as the controller does — without HTTP,
PNG encoding, JSON or the database. ``wall / floor`` says how far a search is from the work it
cannot avoid; ``wall / pipeline`` what the microservices cost over the same work in one process.

Each sampled target's search is run again through the stack just before its in-process
measurements, so the three times of one sample see the same machine load.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from cosmos.bench.runner import BenchTarget, SearchRecord, run_searches
from cosmos.bench.stats import percentile
from services.common.catalog import SceneCatalog
from services.common.contracts.detect import Detection
from services.common.contracts.optimize import (
    NextPoseRequest,
    StrategyName,
    TargetImage,
    VisitedView,
    searchable_grid,
)
from services.common.geometry.pose import GridIndex, PoseQuery
from services.common.geometry.scene import LoadedScene
from services.common.images import decode_image

__all__ = ["DEFINITION", "InProcess", "ProfileSample", "profile_searches", "profile_summary"]

DEFINITION: Final = (
    "*floor* = detect the target (decode, letterbox, inference, post-processing) + render and "
    "detect the start view + render and detect the final view (when it differs from the start), "
    "timed serially in one process with the services' own RenderEngine and DetectorModel, warm, "
    "views detected from their arrays. *one-process pipeline* = the same renders, detections and "
    "optimizer calls the search made, in one process without HTTP, PNG, JSON or the database (the "
    "target's detection overlapping the start render, as in the controller). *wall* = the same "
    "search run again through the stack just before, from POST to its end event. Each of the three "
    "is the median of 3 such rounds per target; ratios are per target, the table gives their "
    "median and p95."
)

View = tuple[tuple[int, int], tuple[Detection, ...]]


@dataclass(frozen=True)
class ProfileSample:
    """One target: the real search's wall time, its floor and its one-process pipeline (ms)."""

    scene: str
    number: int
    renders: int
    wall_ms: float
    floor_ms: float
    pipeline_ms: float
    target_detect_ms: float
    start_render_ms: float
    start_detect_ms: float
    final_render_ms: float
    final_detect_ms: float

    @property
    def floor_ratio(self) -> float:
        return self.wall_ms / self.floor_ms

    @property
    def stack_ratio(self) -> float:
        return self.wall_ms / self.pipeline_ms


class InProcess:
    """The renderer's engine, the detector's model and the optimizer's planning in this process.

    Reads the same ``COSMOS_*`` settings as the services, so it loads the same scenes, Mitsuba
    variant, detector model and calibrations, and renders the views the controller would ask
    for (its ``render_spp`` and ``render_width`` unless given here).
    """

    def __init__(self, render_spp: int | None = None, render_width: int | None = None) -> None:
        from services.controller.settings import ControllerSettings
        from services.detector.detect import DetectOptions
        from services.detector.model import DetectorModel
        from services.detector.settings import DetectorSettings
        from services.optimizer.settings import OptimizerSettings
        from services.optimizer.wiring import build_optimizer
        from services.renderer.settings import RendererSettings
        from services.renderer.wiring import build_renderer

        renderer = RendererSettings()
        controller = ControllerSettings()
        self.catalog = SceneCatalog(renderer.scene_directories())
        # What the controller asks the renderer for (its settings, else the renderer's default).
        self.spp = render_spp or controller.controller_view_spp or renderer.renderer_default_spp
        self.width = render_width or controller.controller_view_width
        self.engine = build_renderer(renderer).engine
        self.engine.start()
        self.detector_settings = DetectorSettings()
        self.model = DetectorModel(
            self.detector_settings.detector_model, threads=self.detector_settings.detector_threads
        )
        self.options = DetectOptions.from_settings(self.detector_settings)
        self.context = build_optimizer(OptimizerSettings())
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="target-detect")

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self.engine.close()

    def render(self, scene: LoadedScene, index: GridIndex) -> NDArray[np.uint8]:
        """The view the controller would get for grid pose ``index`` (seed 0, this spp and film
        width; the height keeps the scene's aspect as the renderer's does)."""
        camera = scene.spec.camera
        width, height = camera.width, camera.height
        if self.width is not None:
            width, height = self.width, max(8, round(self.width / (camera.width / camera.height)))
        pose = scene.spec.search.grid().pose(index)
        return self.engine.render(scene, pose, width, height, self.spp, 0).rgb

    def detect_rgb(self, rgb: NDArray[np.uint8]) -> View:
        """What ``POST /detect`` answers for this image, without the HTTP and the codec."""
        from services.detector.detect import detections_from_output
        from services.detector.letterbox import letterbox

        tensor, box = letterbox(rgb, self.model.layout.input_size)
        output = self.model.run(tensor[np.newaxis])[0]
        detections = detections_from_output(output, box, self.model.classes, rgb, self.options)
        return box.image_size, detections

    def detect_bytes(self, data: bytes) -> View:
        """Detection of an uploaded image: decode, then :meth:`detect_rgb`."""
        settings = self.detector_settings
        rgb = decode_image(
            data,
            max_pixels=settings.detector_max_image_pixels,
            max_side=settings.detector_max_image_side,
        )
        return self.detect_rgb(rgb)

    def warm_up(self, scenes: Sequence[str]) -> None:
        """Load every scene and pay each first-call cost before anything is timed."""
        for scene_id in scenes:
            scene = self.catalog.get(scene_id)
            for _ in range(2):
                self.detect_rgb(self.render(scene, GridIndex(lat=0, lon=0)))

    def floor(self, record: SearchRecord, image: bytes) -> dict[str, float]:
        """The unavoidable work of ``record``'s search, timed part by part (ms)."""
        scene = self.catalog.get(record.scene)
        start = record.start
        last = record.trajectory[-1] if record.trajectory else None
        final = GridIndex(lat=last.lat, lon=last.lon) if last is not None else start
        parts = {}
        t0 = time.perf_counter()
        self.detect_bytes(image)
        t1 = time.perf_counter()
        rgb = self.render(scene, start)
        t2 = time.perf_counter()
        self.detect_rgb(rgb)
        t3 = time.perf_counter()
        parts["target_detect_ms"] = (t1 - t0) * 1000
        parts["start_render_ms"] = (t2 - t1) * 1000
        parts["start_detect_ms"] = (t3 - t2) * 1000
        parts["final_render_ms"] = parts["final_detect_ms"] = 0.0
        if final != start:
            t4 = time.perf_counter()
            rgb = self.render(scene, final)
            t5 = time.perf_counter()
            self.detect_rgb(rgb)
            t6 = time.perf_counter()
            parts["final_render_ms"] = (t5 - t4) * 1000
            parts["final_detect_ms"] = (t6 - t5) * 1000
        return parts

    def pipeline(self, record: SearchRecord, image: bytes) -> float:
        """Replay ``record``'s search in this process; its wall time in ms."""
        from services.optimizer.planning import next_pose

        scene = self.catalog.get(record.scene)
        spec = scene.spec
        grid = searchable_grid(spec.search)
        started = time.perf_counter()
        pending = self._pool.submit(self.detect_bytes, image)
        target: View | None = None
        views: dict[tuple[int, int], View] = {}
        visited: list[VisitedView] = []
        for step in record.trajectory:
            key = (step.lat, step.lon)
            if key not in views:
                views[key] = self.detect_rgb(self.render(scene, GridIndex(lat=key[0], lon=key[1])))
            if target is None:
                target = pending.result()
            size, detections = views[key]
            visited.append(
                VisitedView(
                    pose=PoseQuery(lat=key[0], lon=key[1]), image_size=size, detections=detections
                )
            )
            next_pose(
                NextPoseRequest(
                    strategy=record.strategy,
                    camera=spec.camera,
                    grid=grid,
                    target=TargetImage(image_size=target[0], detections=target[1]),
                    history=tuple(visited),
                ),
                self.context,
            )
        if target is None:
            pending.result()
        return (time.perf_counter() - started) * 1000


def profile_searches(
    controller_url: str,
    targets: Sequence[BenchTarget],
    *,
    strategy: StrategyName = "reprojection",
    render_spp: int | None = None,
    render_width: int | None = None,
    max_iterations: int = 60,
    repeats: int = 3,
    progress: Callable[[str], None] | None = None,
    api_key: str | None = None,
) -> list[ProfileSample]:
    """For each target, ``repeats`` rounds of: its search through the stack again, its
    one-process pipeline, its floor; each time is the median of its rounds."""
    local = InProcess(render_spp, render_width)
    try:
        local.warm_up(sorted({t.scene for t in targets}))
        samples = []
        for target in targets:
            walls, pipelines, floors = [], [], []
            record = None
            for _ in range(repeats):
                (record,) = run_searches(
                    controller_url,
                    [(target, strategy)],
                    max_iterations=max_iterations,
                    api_key=api_key,
                )
                if record.status == "error" or not record.trajectory:
                    break
                walls.append(record.wall_ms)
                pipelines.append(local.pipeline(record, target.image))
                floors.append(local.floor(record, target.image))
            if record is None or not walls:
                continue
            parts = {key: statistics.median(f[key] for f in floors) for key in floors[0]}
            sample = ProfileSample(
                scene=target.scene,
                number=target.number,
                renders=record.renders,
                wall_ms=statistics.median(walls),
                floor_ms=statistics.median(sum(f.values()) for f in floors),
                pipeline_ms=statistics.median(pipelines),
                **parts,
            )
            samples.append(sample)
            if progress is not None:
                progress(
                    f"profile {target.scene} #{target.number}: wall {sample.wall_ms:.0f} ms, "
                    f"floor {sample.floor_ms:.0f} ms ({sample.floor_ratio:.2f}x), one process "
                    f"{sample.pipeline_ms:.0f} ms ({sample.stack_ratio:.2f}x)"
                )
        return samples
    finally:
        local.close()


def profile_summary(samples: Sequence[ProfileSample]) -> dict[str, Any]:
    """Per scene and overall: medians of the times and of the per-search ratios."""
    rows = []
    for scene in [*sorted({s.scene for s in samples}), "all"]:
        mine = [s for s in samples if scene in ("all", s.scene)]
        if not mine:
            continue
        rows.append(
            {
                "scene": scene,
                "n": len(mine),
                "wall_p50_ms": statistics.median(s.wall_ms for s in mine),
                "floor_p50_ms": statistics.median(s.floor_ms for s in mine),
                "pipeline_p50_ms": statistics.median(s.pipeline_ms for s in mine),
                "floor_ratio_p50": statistics.median(s.floor_ratio for s in mine),
                "floor_ratio_p95": percentile([s.floor_ratio for s in mine], 95),
                "stack_ratio_p50": statistics.median(s.stack_ratio for s in mine),
                "stack_ratio_p95": percentile([s.stack_ratio for s in mine], 95),
            }
        )
    parts = (
        "target_detect_ms",
        "start_render_ms",
        "start_detect_ms",
        "final_render_ms",
        "final_detect_ms",
    )
    return {
        "definition": DEFINITION,
        "rows": rows,
        "floor_parts_p50_ms": {
            p.removesuffix("_ms").replace("_", " "): statistics.median(
                float(getattr(s, p)) for s in samples
            )
            for p in parts
        }
        if samples
        else {},
        "samples": [asdict(s) for s in samples],
    }
