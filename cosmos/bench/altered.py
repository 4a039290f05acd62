"""Modified copies of a scene, for targets of a scene that is not quite the one searched.

``photo`` moves the point light and scales its intensity; ``changed`` moves one object on the
ground or leaves it out (:mod:`cosmos.bench.variants` says what each variant is for). A copy is
written as its own scene, ``<folder>/<id>.yaml``, with the source's assets copied once into
``<folder>/<source id>.assets/`` (an asset path may not leave its scene's folder), so that a
renderer whose ``COSMOS_SCENES_DIR`` includes ``folder`` renders it by id. Camera and search
grid stay the source's: a target's grid pose means the same in both.

Light (``photo``): in spherical coordinates about the origin, the azimuth turns by ±[30°, 90°],
the polar angle moves by ±[5°, 20°] within [5°, 70°], the distance scales by [0.8, 1.25] and the
intensity by [0.5, 2].
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from pydantic import ValidationError

from cosmos.bench.scenes import GAP, footprint, write_scene_yaml
from cosmos.bench.variants import Variant
from services.common.geometry.scene import LoadedScene, SceneSpec

__all__ = ["LEAVE_OUT_SHARE", "MOVE_RANGE", "AlteredScene", "alter_scene", "changed", "photo"]

MOVE_RANGE: Final = (0.5, 1.5)
"""How far ``changed`` moves an object on the ground, in scene units."""
LEAVE_OUT_SHARE: Final = 0.3
"""The share of ``changed`` targets whose object is left out rather than moved."""
INTENSITY_RANGE: Final = (0.5, 2.0)


@dataclass(frozen=True)
class AlteredScene:
    """A written copy: its id and what was changed, in words for the report."""

    id: str
    change: str


def _document(scene: LoadedScene) -> dict[str, Any]:
    data: dict[str, Any] = scene.spec.model_dump(mode="json", exclude_none=True)
    return data


def photo(data: dict[str, Any], rng: np.random.Generator) -> str:
    """Move and scale ``data``'s point light in place (module docstring); what changed."""
    point = data["lighting"]["point"]
    x, y, z = point["position"]
    r = math.sqrt(x * x + y * y + z * z)
    theta, phi = math.acos(z / r), math.atan2(y, x)
    turn = math.radians(rng.uniform(30, 90)) * float(rng.choice([-1.0, 1.0]))
    tilt = math.radians(rng.uniform(5, 20)) * float(rng.choice([-1.0, 1.0]))
    theta = min(max(theta + tilt, math.radians(5)), math.radians(70))
    r *= float(rng.uniform(0.8, 1.25))
    phi += turn
    point["position"] = [
        round(r * math.sin(theta) * math.cos(phi), 4),
        round(r * math.sin(theta) * math.sin(phi), 4),
        round(r * math.cos(theta), 4),
    ]
    factor = float(rng.uniform(*INTENSITY_RANGE))
    point["intensity"] = round(point["intensity"] * factor, 4)
    return (
        f"light turned {math.degrees(turn):+.0f}° about z, tilted {math.degrees(tilt):+.0f}°, "
        f"intensity ×{factor:.2f}"
    )


def changed(scene: LoadedScene, data: dict[str, Any], rng: np.random.Generator) -> str:
    """Move one object of ``data`` by :data:`MOVE_RANGE` on the ground (clear of the others and
    inside the ground square), or, with :data:`LEAVE_OUT_SHARE` (and more than one object), leave
    it out; in place. What changed."""
    objects = data["objects"]
    i = int(rng.integers(len(objects)))
    name = objects[i]["name"]
    if len(objects) > 1 and rng.random() < LEAVE_OUT_SHARE:
        del objects[i]
        return f"{name} left out"
    discs = [(*o.position, *footprint(o, scene.directory)) for o in scene.spec.objects]
    half = scene.spec.ground.size / 2.0
    x0, y0, reach, _ = discs[i]
    for _ in range(100):
        distance = float(rng.uniform(*MOVE_RANGE))
        angle = float(rng.uniform(0, 2 * math.pi))
        x, y = x0 + distance * math.cos(angle), y0 + distance * math.sin(angle)
        inside = max(abs(x), abs(y)) + reach <= half
        clear = all(
            math.hypot(x - ox, y - oy) >= reach + r + GAP
            for j, (ox, oy, r, _) in enumerate(discs)
            if j != i
        )
        if not (inside and clear):
            continue
        objects[i]["position"] = [round(x, 4), round(y, 4)]
        try:
            SceneSpec.model_validate(data)  # the camera must still clear it
        except ValidationError:
            continue
        return f"{name} moved {distance:.2f} towards {math.degrees(angle):.0f}°"
    if len(objects) > 1:  # nowhere to go: the other change
        del objects[i]
        return f"{name} left out (no room to move it)"
    raise ValueError(f"{scene.id}: its only object has no room to move")


def _copy_assets(scene: LoadedScene, data: dict[str, Any], folder: Path) -> None:
    """Point ``data``'s asset paths at copies in ``folder/<source id>.assets/`` (copied once)."""
    prefix = f"{scene.id}.assets"
    for field, source in scene.assets.items():
        relative = scene.spec.asset_paths()[field]
        target = folder / prefix / relative
        if not target.exists() or target.stat().st_size != source.stat().st_size:
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
    new = f"{prefix}/"
    ground = data["ground"]
    if "texture" in ground:
        ground["texture"] = new + ground["texture"]
    for obj in data["objects"]:
        for key in ("texture", "file"):
            if key in obj:
                obj[key] = new + obj[key]


def alter_scene(
    scene: LoadedScene,
    variant: Variant,
    rng: np.random.Generator,
    folder: Path,
    scene_id: str,
) -> AlteredScene:
    """Write the ``variant`` copy of ``scene`` as ``folder/<scene_id>.yaml`` (module docstring)."""
    data = _document(scene)
    if variant == "photo":
        change = photo(data, rng)
    elif variant == "changed":
        change = changed(scene, data, rng)
    else:
        raise ValueError(f"{variant!r} targets are rendered from the scene itself")
    _copy_assets(scene, data, folder)
    write_scene_yaml(folder / f"{scene_id}.yaml", data)
    return AlteredScene(scene_id, change)
