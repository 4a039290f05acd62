"""Render a labelled detection dataset with the project's renderer (domain randomisation).

Run ``python -m training.dataset --out data/train --count 3000 --seed 1``; it resumes where it
stopped (a sample is done when its label file exists), so it can run in chunks.

Every scene is random: 1–10 objects of the detector's classes (sphere, cube, cylinder, cone, mesh),
any size, colour (any hue, greys and dark ones included) or texture, touching and partly occluding;
a plain or textured ground of random colour; a point light anywhere above the ground with random
intensity and ambient; a camera of random fov and radius. Each scene is seen from
``views_per_scene`` random poses over the whole hemisphere at one random image size, or, for a
share ``drone_share`` of the views, from a drone (:func:`~training.drone_views.drone_camera`: any
distance, mostly down, rolled, fov ±30 %). A share of the scenes are the built-in ``demo`` and
``garden`` from random poses. Labels come from the renderer's ground truth (per-pixel shape ids),
so occlusion and image edges are exact.

Sample ``i`` of seed ``s`` depends only on ``(s, i)`` (and the drone share): datasets are
reproducible, and a held-out set is one rendered with a seed never used for training. Whether a
view is a drone's is drawn from a stream of its own, so a dataset rendered without drone views is
the one it always was. The folder keeps its arguments in ``dataset.json`` (:data:`RECIPE_FILE`);
a model's provenance and card carry them on, so its card can say how to render its data again.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scene_assets import value_noise
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.render import ObjectAnnotation, RenderAnnotations
from services.common.geometry.free_camera import FreeCamera
from services.common.geometry.pose import Pose
from services.common.geometry.scene import LoadedScene, SceneSpec
from services.renderer.engine import RenderEngine
from services.renderer.imaging import encode_png
from training.drone_views import drone_camera, engine_view

__all__ = [
    "View",
    "asset_folder",
    "dataset_command",
    "dataset_recipe",
    "labelled_objects",
    "views",
    "CLASSES",
    "IMAGE_SIZES",
    "RECIPE_FILE",
    "LabelledObject",
    "Sample",
    "main",
    "random_scene",
    "render_dataset",
]

CLASSES: tuple[str, ...] = ("sphere", "cube", "cylinder", "cone", "mesh")
IMAGE_SIZES: tuple[tuple[int, int], ...] = (
    (320, 240),
    (320, 240),
    (320, 240),
    (256, 192),
    (400, 300),
    (320, 320),
    (384, 216),
    (240, 320),
)
MESHES = ("meshes/duck.ply", "meshes/arch.ply")
TEXTURES = ("textures/tiles.png", "textures/wood.png", "textures/duck.png")
RANDOM_TEXTURES = 16
MIN_LABEL_PIXELS = 6  # objects with fewer visible pixels are not labelled (nothing to see)


@dataclass(frozen=True)
class LabelledObject:
    """One labelled object of a sample."""

    cls: str
    box: tuple[float, float, float, float]
    visible_pixels: int
    visible_fraction: float


@dataclass(frozen=True)
class Sample:
    """One rendered image and its labels."""

    index: int
    scene: str
    width: int
    height: int
    pose: Pose | FreeCamera
    objects: tuple[LabelledObject, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "image": f"images/{self.index:06d}.png",
            "scene": self.scene,
            "width": self.width,
            "height": self.height,
            "pose": self.pose.model_dump(),
            "objects": [
                {
                    "class": o.cls,
                    "class_id": CLASSES.index(o.cls),
                    "box": list(o.box),
                    "visible_pixels": o.visible_pixels,
                    "visible_fraction": o.visible_fraction,
                }
                for o in self.objects
            ],
        }


def _random_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """Linear RGB reflectance: saturated hues, pastels, greys and dark colours alike."""
    kind = rng.random()
    if kind < 0.15:  # grey, from near-black to near-white
        v = float(rng.uniform(0.02, 0.9))
        return (v, v, v)
    hue = rng.uniform(0, 6)
    sat = rng.uniform(0.3, 1.0) if kind < 0.85 else rng.uniform(0.05, 0.3)
    val = rng.uniform(0.05, 0.9)
    c = val * sat
    x = c * (1 - abs(hue % 2 - 1))
    rgb = [(c, x, 0), (x, c, 0), (0, c, x), (0, x, c), (x, 0, c), (c, 0, x)][int(hue) % 6]
    m = val - c
    return tuple(float(np.clip(v + m, 0.0, 1.0)) for v in rgb)  # type: ignore[return-value]


def random_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A procedural RGB texture: a checker, stripes or smooth noise in random colours."""
    a = (np.array(_random_colour(rng)) ** (1 / 2.2) * 255).astype(np.float32)
    b = (np.array(_random_colour(rng)) ** (1 / 2.2) * 255).astype(np.float32)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    kind = rng.integers(3)
    if kind == 0:
        n = int(rng.integers(2, 12))
        t = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float32)
    elif kind == 1:
        freq = float(rng.uniform(2, 20))
        angle = rng.uniform(0, math.pi)
        t = (np.sin((x * math.cos(angle) + y * math.sin(angle)) * freq * 2 * math.pi) > 0).astype(
            np.float32
        )
    else:
        t = value_noise(rng, (size, size), (8, 8))
    image = a[None, None, :] * (1 - t[..., None]) + b[None, None, :] * t[..., None]
    image += rng.normal(0, 6, image.shape).astype(np.float32)
    out: np.ndarray = np.clip(image, 0, 255).astype(np.uint8)
    return out


def _place(
    rng: np.random.Generator,
    footprints: list[tuple[float, float, float]],
    reach: float,
    spread: float,
) -> tuple[float, float] | None:
    """A footprint centre that does not overlap the others much (touching is allowed)."""
    for _ in range(40):
        x, y = rng.uniform(-spread, spread, 2)
        if all(math.hypot(x - ox, y - oy) >= 0.85 * (reach + orad) for ox, oy, orad in footprints):
            return float(x), float(y)
    return None


def _random_object(
    rng: np.random.Generator, textures: Sequence[str]
) -> tuple[dict[str, Any], float]:
    """A random object's fields (without name and position) and its footprint radius."""
    cls = CLASSES[int(rng.choice(len(CLASSES), p=[0.28, 0.2, 0.2, 0.17, 0.15]))]
    fields: dict[str, Any] = {"shape": cls}
    if rng.random() < 0.2:
        fields["texture"] = str(rng.choice(textures))
    else:
        fields["color"] = _random_colour(rng)
    if cls != "sphere":
        fields["yaw_deg"] = float(rng.uniform(0, 360))
    if cls == "sphere":
        fields["radius"] = float(rng.uniform(0.2, 0.7))
        return fields, fields["radius"]
    if cls == "cube":
        fields["size"] = float(rng.uniform(0.3, 1.1))
        return fields, fields["size"] * 0.71
    if cls in ("cylinder", "cone"):
        fields["radius"] = float(rng.uniform(0.12, 0.55))
        fields["height"] = float(rng.uniform(0.3, 1.4))
        return fields, fields["radius"]
    fields["file"] = str(rng.choice(MESHES))
    fields["scale"] = float(rng.uniform(0.3, 0.9))
    if fields["file"].endswith("duck.ply") and rng.random() < 0.6:
        fields.pop("color", None)
        fields["texture"] = "textures/duck.png"
    return fields, 0.9 * fields["scale"]


def random_scene(rng: np.random.Generator, textures: Sequence[str]) -> SceneSpec:
    """A random scene spec whose texture and mesh paths are relative to the asset folder."""
    ground_size = float(rng.uniform(8, 14))
    spread = float(rng.uniform(1.2, min(3.5, ground_size / 2 - 1)))
    objects: list[dict[str, Any]] = []
    footprints: list[tuple[float, float, float]] = []
    for i in range(int(rng.integers(1, 11))):
        fields, reach = _random_object(rng, textures)
        position = _place(rng, footprints, reach, spread)
        if position is not None:
            objects.append({"name": f"o{i}", "position": position, **fields})
            footprints.append((position[0], position[1], reach))
    ground: dict[str, Any] = {"size": ground_size}
    if rng.random() < 0.35:
        ground["texture"] = str(rng.choice(textures))
    else:
        ground["color"] = _random_colour(rng)
    light_theta = rng.uniform(0, math.radians(70))
    light_phi = rng.uniform(0, 2 * math.pi)
    light_r = rng.uniform(5, 12)
    light = (
        light_r * math.sin(light_theta) * math.cos(light_phi),
        light_r * math.sin(light_theta) * math.sin(light_phi),
        light_r * math.cos(light_theta),
    )
    return SceneSpec.model_validate(
        {
            "camera": {
                "fov_deg": float(rng.uniform(35, 60)),
                "width": 320,
                "height": 240,
                "radius": float(rng.uniform(6.5, 11)),
            },
            "lighting": {
                "point": {"position": light, "intensity": float(rng.uniform(60, 400))},
                "ambient": float(rng.uniform(0.0, 0.4)),
            },
            "ground": ground,
            "objects": objects,
        }
    )


def asset_folder(out: Path) -> Path:
    """The folder holding the dataset's meshes and textures (the shipped ones and random ones)."""
    folder = out / "assets"
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    for relative in (*MESHES, *TEXTURES):
        target = folder / relative
        if not target.exists():
            target.write_bytes((BUILTIN_SCENES_DIR / relative).read_bytes())
    rng = np.random.default_rng(12345)
    for k in range(RANDOM_TEXTURES):
        target = folder / "textures" / f"random{k:02d}.png"
        texture = random_texture(rng)
        if not target.exists():
            target.write_bytes(encode_png(texture))
    return folder


def _loaded(spec: SceneSpec, scene_id: str, folder: Path) -> LoadedScene:
    assets = {
        field: (folder / relative).resolve() for field, relative in spec.asset_paths().items()
    }
    return LoadedScene(id=scene_id, path=folder / f"{scene_id}.yaml", spec=spec, assets=assets)


def labelled_objects(ann: RenderAnnotations) -> list[ObjectAnnotation]:
    """The objects of a view worth a label: at least :data:`MIN_LABEL_PIXELS` visible pixels
    and a box at least 2 pixels wide and high."""
    labelled = []
    for obj in ann.objects:
        if obj.box is None or obj.visible_pixels < MIN_LABEL_PIXELS:
            continue
        x1, y1, x2, y2 = obj.box
        if x2 - x1 >= 2 and y2 - y1 >= 2:
            labelled.append(obj)
    return labelled


def _labels(ann: RenderAnnotations) -> tuple[LabelledObject, ...]:
    return tuple(
        LabelledObject(
            cls=obj.shape,
            box=obj.box,
            visible_pixels=obj.visible_pixels,
            visible_fraction=round(obj.visible_fraction, 4),
        )
        for obj in labelled_objects(ann)
        if obj.box is not None
    )


@dataclass(frozen=True)
class View:
    """One view to render: sample ``index`` of a dataset."""

    index: int
    scene: LoadedScene
    pose: Pose | FreeCamera
    width: int
    height: int
    spp: int
    seed: int


def views(
    assets: Path,
    seed: int,
    count: int,
    views_per_scene: int = 4,
    builtin_share: float = 0.15,
    skip: Callable[[range], bool] | None = None,
    drone_share: float = 0.0,
) -> Iterator[View]:
    """The views ``0 .. count-1`` of dataset ``seed`` (groups for which ``skip`` is true are
    left out); ``assets`` is a folder prepared by :func:`asset_folder`."""
    textures = [*TEXTURES, *(f"textures/random{k:02d}.png" for k in range(RANDOM_TEXTURES))]
    builtin = SceneCatalog([BUILTIN_SCENES_DIR])
    for first in range(0, count, views_per_scene):
        group = range(first, min(first + views_per_scene, count))
        if skip is not None and skip(group):
            continue
        rng = np.random.default_rng([seed, first])
        if rng.random() < builtin_share:
            scene = builtin.get(str(rng.choice(["demo", "garden"])))
        else:
            scene = _loaded(random_scene(rng, textures), f"s{seed}-{first}", assets)
        width, height = IMAGE_SIZES[int(rng.integers(len(IMAGE_SIZES)))]
        for i in group:
            pose: Pose | FreeCamera = Pose(
                theta_deg=float(np.degrees(np.arccos(rng.uniform(0.06, 1.0)))),
                phi_deg=float(rng.uniform(0, 360)),
            )
            drone = np.random.default_rng([seed, i, 2])
            if drone.random() < drone_share:
                pose = drone_camera(scene, drone)
            spp = int(rng.choice([8, 16, 32]))
            yield View(i, scene, pose, width, height, spp, int(rng.integers(2**31)))


RECIPE_FILE = "dataset.json"
"""Written into a dataset's folder: the arguments that render it again."""


def dataset_recipe(root: Path) -> dict[str, Any] | None:
    """The arguments ``root`` was rendered with (``None`` for a dataset older than its
    recipe file)."""
    path = root / RECIPE_FILE
    return json.loads(path.read_text()) if path.exists() else None


def dataset_command(root: str, recipe: Mapping[str, Any]) -> str:
    """The command that renders the dataset ``root`` of ``recipe`` again."""
    return (
        f".venv/bin/python -m training.dataset --out {root} --count {recipe['count']} "
        f"--seed {recipe['seed']} --views-per-scene {recipe['views_per_scene']} "
        f"--builtin-share {recipe['builtin_share']} --drone-share {recipe['drone_share']}"
    )


def render_dataset(
    out: Path,
    count: int,
    seed: int,
    views_per_scene: int = 4,
    builtin_share: float = 0.15,
    drone_share: float = 0.0,
) -> int:
    """Render samples ``0 .. count-1`` of ``seed`` into ``out`` (skipping finished ones).

    Returns the number of samples rendered now.
    """
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    recipe = {
        "count": count,
        "seed": seed,
        "views_per_scene": views_per_scene,
        "builtin_share": builtin_share,
        "drone_share": drone_share,
    }
    (out / RECIPE_FILE).write_text(json.dumps(recipe, indent=2) + "\n")

    def finished(group: range) -> bool:
        return all((out / "labels" / f"{i:06d}.json").exists() for i in group)

    engine = RenderEngine("auto", cache_size=2)
    engine.start()
    done = 0
    started = time.perf_counter()
    try:
        todo = views(
            asset_folder(out), seed, count, views_per_scene, builtin_share, finished, drone_share
        )
        for view in todo:
            where = engine_view(view.scene, view.pose, view.width, view.height)
            image = engine.render(
                view.scene, where, view.width, view.height, view.spp, seed=view.seed
            )
            ann = engine.annotate(view.scene, where, view.width, view.height, None)
            sample = Sample(
                view.index, view.scene.id, view.width, view.height, view.pose, _labels(ann)
            )
            (out / "images" / f"{view.index:06d}.png").write_bytes(encode_png(image.rgb))
            label = out / "labels" / f"{view.index:06d}.json"
            label.with_suffix(".tmp").write_text(json.dumps(sample.to_json()))
            label.with_suffix(".tmp").replace(label)
            done += 1
            if done % 100 == 0:
                rate = done / (time.perf_counter() - started)
                print(f"{view.index + 1}/{count} samples ({rate:.1f}/s)", flush=True)
    finally:
        engine.close()
    return done


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Render a labelled detection dataset.")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--count", type=int, required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--views-per-scene", type=int, default=4)
    parser.add_argument("--builtin-share", type=float, default=0.15)
    parser.add_argument(
        "--drone-share", type=float, default=0.0, help="share of the views taken from a drone"
    )
    args = parser.parse_args(argv)
    started = time.perf_counter()
    done = render_dataset(
        args.out,
        args.count,
        args.seed,
        args.views_per_scene,
        args.builtin_share,
        args.drone_share,
    )
    elapsed = time.perf_counter() - started
    print(f"rendered {done} samples into {args.out} in {elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
