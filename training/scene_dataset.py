"""Render one scene's auto-labelled detection dataset: its own objects as classes, from any pose.

Sample ``i`` of seed ``s`` depends only on ``(s, i)``, so a held-out set is the same scene rendered
with another seed, and an interrupted run resumes where it stopped (a sample is done when its
label file exists). What varies from sample to sample:

- the pose: of every six samples, two are grid poses of the scene's search grid, two lie anywhere
  in its θ range ``[min_theta_deg, max_theta_deg]`` (uniform in cos θ) and at any φ, so the model
  sees the views between grid poses that an off-grid target shows, and two are drone views
  (:func:`~training.drone_views.drone_camera`): anywhere, looking anywhere at the objects,
  mostly down, rolled, through another lens. A model trained on the hemisphere alone found 1 of 3
  objects in such views of a generated scene (``cosmos bench --free --onboard``, seed 2), where
  the general model found 3;
- the lighting, per group of :data:`VIEWS_PER_LIGHTING` consecutive samples (each lighting is a
  scene load): the point light moves to a random place above the ground at 0.7–1.4 times its
  distance, its intensity is scaled by ``2^u``, ``u ~ U(-1, 1)`` (×0.5–2), the ambient by
  ``U(0.5, 1.5)`` plus ``U(0, 0.05)``; the renderer gets a modified copy of the spec;
- samples per pixel: 8, 16 or 32 with probabilities 0.5, 0.3, 0.2 (the search's noise level
  and cleaner).

The film is the scene's own. Boxes, visible pixels and visible fractions come from the renderer's
ground truth (:meth:`~services.renderer.engine.RenderEngine.annotate`); an object's class id is
its class's index in :func:`~services.common.scene_models.object_classes`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.common.contracts.render import RenderAnnotations
from services.common.geometry.free_camera import FreeCamera
from services.common.geometry.pose import Pose
from services.common.geometry.scene import Lighting, LoadedScene, PointLight
from services.common.scene_models import object_classes
from services.renderer.engine import RenderEngine
from services.renderer.imaging import encode_png
from training.dataset import labelled_objects
from training.drone_views import drone_camera, engine_view

__all__ = [
    "VIEWS_PER_LIGHTING",
    "SceneView",
    "class_ids",
    "finished_samples",
    "jittered_lighting",
    "render_scene_dataset",
    "scene_views",
]

VIEWS_PER_LIGHTING = 8
SPP_CHOICES = (8, 16, 32)
SPP_WEIGHTS = (0.5, 0.3, 0.2)  # a 32-spp render costs ~3x an 8-spp one; the search renders at 8


@dataclass(frozen=True)
class SceneView:
    """Sample ``index``: the scene (with its lighting for this sample), a hemisphere pose or a
    free camera, spp and seed."""

    index: int
    scene: LoadedScene
    pose: Pose | FreeCamera
    spp: int
    seed: int


def class_ids(scene: LoadedScene) -> dict[str, int]:
    """Object name -> class id of the scene's own detector."""
    return {name: k for k, cls in enumerate(object_classes(scene.spec)) for name in cls.objects}


def jittered_lighting(lighting: Lighting, rng: np.random.Generator) -> Lighting:
    """A random relighting of ``lighting`` (module docstring)."""
    distance = math.dist(lighting.point.position, (0.0, 0.0, 0.0)) or 8.0
    r = distance * rng.uniform(0.7, 1.4)
    theta, phi = math.radians(rng.uniform(0.0, 70.0)), rng.uniform(0.0, 2 * math.pi)
    position = (
        r * math.sin(theta) * math.cos(phi),
        r * math.sin(theta) * math.sin(phi),
        r * math.cos(theta),
    )
    intensity = lighting.point.intensity * 2.0 ** rng.uniform(-1.0, 1.0)
    ambient = min(100.0, lighting.ambient * rng.uniform(0.5, 1.5) + rng.uniform(0.0, 0.05))
    return Lighting(point=PointLight(position=position, intensity=intensity), ambient=ambient)


def _relit(scene: LoadedScene, seed: int, group: int) -> LoadedScene:
    rng = np.random.default_rng([seed, group, 1])
    spec = scene.spec.model_copy(update={"lighting": jittered_lighting(scene.spec.lighting, rng)})
    # Its own id and version: the render engine caches loaded scenes by both.
    return LoadedScene(
        id=f"{scene.id}~{seed}-{group}",
        path=scene.path,
        spec=spec,
        assets=scene.assets,
        version=scene.version,
    )


def scene_views(
    scene: LoadedScene, seed: int, count: int, skip: Callable[[int], bool] | None = None
) -> Iterator[SceneView]:
    """The views ``0 .. count-1`` of dataset ``seed`` of ``scene`` (those ``skip`` rejects are
    left out), a lighting group at a time."""
    grid = scene.spec.search.grid()
    search = scene.spec.search
    lo, hi = math.radians(search.min_theta_deg), math.radians(search.max_theta_deg)
    for first in range(0, count, VIEWS_PER_LIGHTING):
        group = range(first, min(first + VIEWS_PER_LIGHTING, count))
        todo = [i for i in group if skip is None or not skip(i)]
        if not todo:
            continue
        relit = _relit(scene, seed, first // VIEWS_PER_LIGHTING)
        for i in todo:
            rng = np.random.default_rng([seed, i])
            pose: Pose | FreeCamera
            if i % 3 == 2:
                pose = drone_camera(scene, rng)
            elif i % 3 == 0:
                pose = grid.pose(grid.unflat(int(rng.integers(grid.size))))
            else:
                cos_theta = rng.uniform(math.cos(hi), math.cos(lo))
                pose = Pose(
                    theta_deg=float(np.clip(np.degrees(np.arccos(cos_theta)), 0.0, 90.0)),
                    phi_deg=float(rng.uniform(0.0, 360.0)),
                )
            spp = int(rng.choice(SPP_CHOICES, p=SPP_WEIGHTS))
            yield SceneView(i, relit, pose, spp, int(rng.integers(2**31)))


def _label(
    view: SceneView, ann: RenderAnnotations, ids: dict[str, int], width: int, height: int
) -> dict[str, Any]:
    objects = [
        {
            "class": obj.name,
            "class_id": ids[obj.name],
            "box": list(obj.box or ()),
            "visible_pixels": obj.visible_pixels,
            "visible_fraction": round(obj.visible_fraction, 4),
        }
        for obj in labelled_objects(ann)
    ]
    return {
        "index": view.index,
        "image": f"images/{view.index:06d}.png",
        "scene": view.scene.id.split("~")[0],
        "width": width,
        "height": height,
        "pose": view.pose.model_dump(),
        "spp": view.spp,
        "lighting": view.scene.spec.lighting.model_dump(),
        "objects": objects,
    }


def finished_samples(out: Path, count: int) -> int:
    """How many of samples ``0 .. count-1`` under ``out`` are done."""
    return sum((out / "labels" / f"{i:06d}.json").exists() for i in range(count))


def render_scene_dataset(
    engine: RenderEngine,
    scene: LoadedScene,
    out: Path,
    count: int,
    seed: int,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Render samples ``0 .. count-1`` of ``seed`` into ``out`` (skipping finished ones) with a
    started ``engine``; ``progress(done)`` is told the number of finished samples after each.

    Returns the number of samples rendered now.
    """
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    width, height = scene.spec.camera.width, scene.spec.camera.height
    ids = class_ids(scene)

    def label_path(i: int) -> Path:
        return out / "labels" / f"{i:06d}.json"

    finished = finished_samples(out, count)
    rendered = 0
    for view in scene_views(scene, seed, count, lambda i: label_path(i).exists()):
        where = engine_view(view.scene, view.pose, width, height)
        image = engine.render(view.scene, where, width, height, view.spp, seed=view.seed)
        ann = engine.annotate(view.scene, where, width, height, None)
        (out / "images" / f"{view.index:06d}.png").write_bytes(encode_png(image.rgb))
        tmp = label_path(view.index).with_suffix(".tmp")
        tmp.write_text(json.dumps(_label(view, ann, ids, width, height)))
        tmp.replace(label_path(view.index))  # the label last: it marks the sample done
        rendered += 1
        if progress is not None:
            progress(finished + rendered)
    return rendered
