"""Random scenes for the bench, made as the training set never makes them.

:func:`generate_scene` writes one scene YAML and its assets (PLY meshes, PNG textures)
into a folder, from a seeded :class:`numpy.random.Generator`. Unlike ``training.dataset``'s
``random_scene`` it uses meshes of shapes the detector never saw in training — extruded star,
L and random star-shaped polygons, lumpy blobs, tapered towers — never the shipped duck or arch;
ground textures of kinds the training set has none of (value-noise "grass", bricks, concentric
rings, cells); near colours and, sometimes, two identical objects.

Layout
------
3–10 objects, footprints (discs of radius ``reach`` about each position) apart by ≥ 0.1, spread
within ``s = k · R tan(fov/2)``, k ∈ [0.45, 0.8], clamped to [1.2, 3.5] (widened by 0.25 while an
object finds no room), so that most objects are in view from most poses. The camera radius ``R`` ∈
[6, 12] is raised when needed to clear every object by half again its reach from the origin: ``R ≥
1.5 · max_i hypot(|p_i| + reach_i, h_i)``. Film 256–480 px wide (4:3, 3:2 or 16:10), fov 35–60°,
grid step Δ ∈ [5°, 10°] in 0.5° steps with rings from θ = Δ to the last ``k Δ ≤ 82°``. The point
light stands at ``r`` ∈ [5, 12], θ ≤ 70°, with intensity ``r² · U(1.8, 4.5)`` (irradiance at the
origin ≈ 1.8–4.5, the built-in scenes' range) and ambient 0.05–0.35.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from scene_assets import read_ply_vertices, value_noise, write_ply
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    LoadedScene,
    MeshObject,
    SceneObject,
    SphereObject,
    load_scene,
)
from services.common.scene_models import model_dir

__all__ = [
    "MESH_KINDS",
    "MeshExtent",
    "footprint",
    "generate_scene",
    "generate_scenes",
    "make_mesh",
    "mesh_extent",
    "scene_summary",
    "write_scene_yaml",
]

MESH_KINDS: Final = ("star", "ell", "polygon", "blob", "tower")
PRIMITIVES: Final = ("sphere", "cube", "cylinder", "cone")
GAP: Final = 0.1
"""Smallest gap between two objects' footprint discs, in scene units."""
RADIUS_MARGIN: Final = 1.5

Vertices = NDArray[np.float64]
Faces = NDArray[np.int32]


# -- meshes ---------------------------------------------------------------------------------


def _prism(outline: Vertices, height: float, top_scale: float = 1.0) -> tuple[Vertices, Faces]:
    """A flat-shaded prism over the star-shaped ``outline`` ``(n, 2)`` (star-shaped about the
    origin, counter-clockwise), its top scaled by ``top_scale`` about the origin.

    Every face has its own vertices, so the renderer's vertex normals are the face normals: sharp
    edges stay sharp. Caps are fans from the origin, valid for any star-shaped outline.
    """
    n = len(outline)
    bottom = np.column_stack([outline, np.zeros(n)])
    top = np.column_stack([outline * top_scale, np.full(n, height)])
    verts: list[Vertices] = []
    faces: list[list[int]] = []

    def add(points: Vertices, tris: list[tuple[int, int, int]]) -> None:
        base = sum(len(v) for v in verts)
        verts.append(points)
        faces.extend([[base + a, base + b, base + c] for a, b, c in tris])

    for i in range(n):
        j = (i + 1) % n
        add(np.stack([bottom[i], bottom[j], top[j], top[i]]), [(0, 1, 2), (0, 2, 3)])
    fan = [(0, 1 + (i + 1) % n, 1 + i) for i in range(n)]  # bottom faces down: clockwise
    add(np.vstack([[0.0, 0.0, 0.0], bottom]), fan)
    add(np.vstack([[0.0, 0.0, height], top]), [(a, c, b) for a, b, c in fan])
    return np.vstack(verts), np.asarray(faces, dtype=np.int32)


def _star(rng: np.random.Generator) -> Vertices:
    points = int(rng.integers(4, 8))
    inner = float(rng.uniform(0.35, 0.6))
    angles = np.arange(2 * points) * math.pi / points
    radii = np.where(np.arange(2 * points) % 2 == 0, 1.0, inner)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def _ell(rng: np.random.Generator) -> Vertices:
    """An L: arms of length 2 and width ``w``; its corner square holds the origin (the fan's
    centre must see every edge)."""
    w = float(rng.uniform(0.6, 1.1))
    a, b = 2.0, float(rng.uniform(1.4, 2.0))
    corner = np.array([[0, 0], [a, 0], [a, w], [w, w], [w, b], [0, b]], dtype=np.float64)
    return corner - w / 2.0


def _polygon(rng: np.random.Generator) -> Vertices:
    """A random star-shaped polygon: 5–9 vertices at sorted angles, radii 0.45–1."""
    n = int(rng.integers(5, 10))
    angles = np.sort(rng.uniform(0, 2 * math.pi, n))
    angles += np.linspace(0, 0.5, n)  # keeps neighbours apart a little
    radii = rng.uniform(0.45, 1.0, n)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def _icosphere(subdivisions: int) -> tuple[Vertices, Faces]:
    """The unit icosphere: an icosahedron whose triangles are split in four ``subdivisions``
    times, midpoints pushed onto the sphere."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    faces = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    points = [np.asarray(v, dtype=np.float64) / np.linalg.norm(v) for v in verts]
    for _ in range(subdivisions):
        middle: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int, middle: dict[tuple[int, int], int] = middle) -> int:
            key = (min(a, b), max(a, b))
            if key not in middle:
                m = points[a] + points[b]
                points.append(m / np.linalg.norm(m))
                middle[key] = len(points) - 1
            return middle[key]

        finer = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            finer += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = finer
    return np.asarray(points), np.asarray(faces, dtype=np.int32)


def _blob(rng: np.random.Generator) -> tuple[Vertices, Faces]:
    """A lumpy blob: the icosphere (3 subdivisions) with radial noise of 3–6 Gaussian bumps,
    ``r(u) = 1 + Σ_k a_k exp((u·c_k − 1) / w_k²)``, a_k ∈ ±[0.15, 0.45], then squashed or
    stretched in z by 0.6–1.3. Vertices are shared: the blob is smooth-shaded."""
    unit, faces = _icosphere(3)
    radius = np.ones(len(unit))
    for _ in range(int(rng.integers(3, 7))):
        centre = rng.normal(size=3)
        centre /= np.linalg.norm(centre)
        amplitude = float(rng.uniform(0.15, 0.45)) * float(rng.choice([-1.0, 1.0]))
        width = float(rng.uniform(0.35, 0.8))
        radius += amplitude * np.exp((unit @ centre - 1.0) / width**2)
    verts = unit * np.clip(radius, 0.4, None)[:, None]
    verts[:, 2] *= float(rng.uniform(0.6, 1.3))
    return verts, faces


def _tower(rng: np.random.Generator) -> tuple[Vertices, Faces]:
    """A tapered prism: a regular 3–8-gon of circumradius 1, height 1.5–3.5, top 0.25–0.85 of
    the base."""
    sides = int(rng.integers(3, 9))
    angles = np.arange(sides) * 2 * math.pi / sides + float(rng.uniform(0, math.pi))
    outline = np.column_stack([np.cos(angles), np.sin(angles)])
    return _prism(outline, float(rng.uniform(1.5, 3.5)), float(rng.uniform(0.25, 0.85)))


def make_mesh(kind: str, rng: np.random.Generator) -> tuple[Vertices, Faces]:
    """The vertices ``(V, 3)`` and triangles ``(F, 3)`` of a random mesh of ``kind``, about unit
    size (footprint radius ≈ 1); the scene's ``scale`` sizes it."""
    if kind == "blob":
        return _blob(rng)
    if kind == "tower":
        return _tower(rng)
    outlines: dict[str, Callable[[np.random.Generator], Vertices]] = {
        "star": _star,
        "ell": _ell,
        "polygon": _polygon,
    }
    if kind not in outlines:
        raise ValueError(f"unknown mesh kind {kind!r}; choose from {', '.join(MESH_KINDS)}")
    return _prism(outlines[kind](rng), float(rng.uniform(0.4, 1.6)))


@dataclass(frozen=True)
class MeshExtent:
    """A mesh's size as the renderer places it (bounding box bottom centre at the origin):
    the largest horizontal distance of a vertex from that centre and the height, unscaled."""

    reach: float
    height: float


def mesh_extent(path: Path) -> MeshExtent:
    """:class:`MeshExtent` of the PLY file at ``path``."""
    xyz = read_ply_vertices(path).astype(np.float64)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    centre = (lo[:2] + hi[:2]) / 2.0
    return MeshExtent(
        reach=float(np.max(np.hypot(*(xyz[:, :2] - centre).T))), height=float(hi[2] - lo[2])
    )


def footprint(obj: SceneObject, scene_dir: Path) -> tuple[float, float]:
    """``(reach, height)`` of an object: the radius of the disc about its position that holds
    its footprint at any yaw, and its height (meshes are measured from their file)."""
    if isinstance(obj, SphereObject):
        return obj.radius, 2 * obj.radius
    if isinstance(obj, CubeObject):
        return obj.size / math.sqrt(2.0), obj.size
    if isinstance(obj, CylinderObject | ConeObject):
        return obj.radius, obj.height
    if isinstance(obj, MeshObject):
        extent = mesh_extent(scene_dir / obj.file)
        return extent.reach * obj.scale, extent.height * obj.scale
    raise TypeError(f"unknown object {obj!r}")


# -- textures and colours -------------------------------------------------------------------


def _hsv_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """A linear-RGB reflectance from a random hue, saturation 0.25–1 and value 0.15–0.9 (one in
    eight a grey)."""
    if rng.random() < 0.125:
        v = float(rng.uniform(0.05, 0.85))
        return (v, v, v)
    hsv = np.array(
        [[[rng.uniform(0, 180), rng.uniform(64, 255), rng.uniform(40, 230)]]], dtype=np.float32
    ).astype(np.uint8)
    srgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0].astype(np.float64) / 255.0
    r, g, b = (float(round(c, 4)) for c in srgb**2.2)
    return (r, g, b)


def _near(colour: tuple[float, ...], rng: np.random.Generator) -> tuple[float, ...]:
    """A colour 0.04–0.1 away from ``colour`` in linear RGB: a look-alike a detector must still
    tell apart (``scene_models`` counts colours within 0.03 as the same)."""
    step = rng.normal(size=3)
    step *= float(rng.uniform(0.04, 0.1)) / np.linalg.norm(step)
    moved = np.clip(np.asarray(colour) + step, 0.0, 1.0)
    return tuple(float(round(c, 4)) for c in moved)


def ground_texture(rng: np.random.Generator, size: int = 256) -> NDArray[np.uint8]:
    """An RGB ground texture: "grass" (value noise), bricks, concentric rings or cells, in two
    random colours with grain."""
    a = np.asarray(_hsv_colour(rng)) ** (1 / 2.2) * 255
    b = np.asarray(_hsv_colour(rng)) ** (1 / 2.2) * 255
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    kind = int(rng.integers(4))
    if kind == 0:
        t = value_noise(rng, (size, size), (4, 4), octaves=4)
    elif kind == 1:
        rows = int(rng.integers(4, 12))
        row = np.floor(y * rows)
        shifted = x * rows / 2 + 0.5 * (row % 2)
        mortar = float(rng.uniform(0.04, 0.12))
        t = (((y * rows) % 1 < mortar) | ((shifted % 1) < mortar / 2)).astype(np.float32)
    elif kind == 2:
        cx, cy = rng.uniform(0.2, 0.8, 2)
        t = (np.sin(np.hypot(x - cx, y - cy) * float(rng.uniform(8, 30)) * math.pi) > 0).astype(
            np.float32
        )
    else:
        seeds = rng.random((int(rng.integers(8, 30)), 2)).astype(np.float32)
        d = np.hypot(x[..., None] - seeds[:, 0], y[..., None] - seeds[:, 1])
        nearest = np.sort(d, axis=-1)
        t = np.clip((nearest[..., 1] - nearest[..., 0]) * 12, 0, 1)
    image = a * (1 - t[..., None]) + b * t[..., None]
    image += rng.normal(0, 5, image.shape)
    out: NDArray[np.uint8] = np.clip(image, 0, 255).astype(np.uint8)
    return out


def _write_png(path: Path, rgb: NDArray[np.uint8]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")


# -- scenes ---------------------------------------------------------------------------------


def write_scene_yaml(path: Path, data: dict[str, Any]) -> Path:
    """Write a scene document as YAML (tuples as lists) and check it with ``load_scene``."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [plain(v) for v in value]
        return value

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(plain(data), sort_keys=False))
    load_scene(path)  # a generator bug must not reach the renderer
    return path


@dataclass
class _Layout:
    """Objects placed so far: their fields, reach and height."""

    objects: list[dict[str, Any]]
    discs: list[tuple[float, float, float, float]]  # x, y, reach, height

    def place(self, rng: np.random.Generator, reach: float, spread: float) -> tuple[float, float]:
        for _ in range(200):
            x, y = (float(round(v, 3)) for v in rng.uniform(-spread, spread, 2))
            if all(math.hypot(x - ox, y - oy) >= reach + r + GAP for ox, oy, r, _ in self.discs):
                return x, y
        raise ValueError("no room")

    def extent(self) -> float:
        return max(math.hypot(math.hypot(x, y) + r, h) for x, y, r, h in self.discs)


def _primitive(shape: str, rng: np.random.Generator) -> tuple[dict[str, Any], float, float]:
    """A primitive's fields (no name, position or appearance), reach and height."""
    yaw = float(round(rng.uniform(0, 360), 2))
    if shape == "sphere":
        r = float(round(rng.uniform(0.25, 0.7), 3))
        return {"shape": shape, "radius": r}, r, 2 * r
    if shape == "cube":
        s = float(round(rng.uniform(0.35, 1.1), 3))
        return {"shape": shape, "size": s, "yaw_deg": yaw}, s / math.sqrt(2.0), s
    r = float(round(rng.uniform(0.15, 0.55), 3))
    h = float(round(rng.uniform(0.3, 1.5), 3))
    return {"shape": shape, "radius": r, "height": h, "yaw_deg": yaw}, r, h


def _new_object(
    rng: np.random.Generator, folder: Path, stem: str, colours: list[tuple[float, ...]]
) -> tuple[dict[str, Any], float, float]:
    """A new object's fields (its mesh or texture written to ``folder/stem.*``), reach and
    height. A quarter of the objects take a colour near an earlier one's."""
    fields: dict[str, Any]
    if rng.random() < 0.5:
        fields, reach, height = _primitive(str(rng.choice(PRIMITIVES)), rng)
    else:
        kind = str(rng.choice(MESH_KINDS))
        file = f"{stem}-{kind}.ply"
        write_ply(folder / file, *make_mesh(kind, rng))
        extent = mesh_extent(folder / file)
        scale = float(round(rng.uniform(0.3, 0.75) / extent.reach, 3))
        fields = {"shape": "mesh", "file": file, "scale": scale}
        fields["yaw_deg"] = float(round(rng.uniform(0, 360), 2))
        reach, height = extent.reach * scale, extent.height * scale
    if colours and rng.random() < 0.25:
        fields["color"] = list(_near(colours[int(rng.integers(len(colours)))], rng))
    elif fields["shape"] != "mesh" and rng.random() < 0.15:  # our meshes carry no UVs
        fields["texture"] = f"{stem}.png"
        _write_png(folder / fields["texture"], ground_texture(rng, 128))
    else:
        fields["color"] = list(_hsv_colour(rng))
    if "color" in fields:
        colours.append(tuple(fields["color"]))
    return fields, reach, height


def generate_scene(rng: np.random.Generator | int, folder: Path, scene_id: str = "random") -> Path:
    """Write a random scene ``folder/<scene_id>.yaml`` and its assets in
    ``folder/<scene_id>.assets/`` (module docstring); the path of the YAML file.

    The same seed writes the same files. A ``<scene_id>.detector/`` model left in ``folder`` by an
    earlier run is removed: it was trained for whatever scene had this id then.
    """
    rng = np.random.default_rng(rng)
    assets = f"{scene_id}.assets"
    shutil.rmtree(folder / assets, ignore_errors=True)
    shutil.rmtree(model_dir(folder / f"{scene_id}.yaml"), ignore_errors=True)
    aspect = float(rng.choice([4 / 3, 4 / 3, 3 / 2, 16 / 10]))
    width = int(rng.integers(16, 31)) * 16
    fov = float(round(rng.uniform(35, 60), 2))
    radius = float(rng.uniform(6, 12))
    half_view = radius * math.tan(math.radians(fov / 2))
    spread = float(np.clip(rng.uniform(0.45, 0.8) * half_view, 1.2, 3.5))

    layout = _Layout([], [])
    colours: list[tuple[float, ...]] = []
    for i in range(int(rng.integers(3, 11))):
        if i > 0 and rng.random() < 0.12:  # two identical objects: same look, new place and yaw
            k = int(rng.integers(i))
            fields = {f: v for f, v in layout.objects[k].items() if f not in ("name", "position")}
            if "yaw_deg" in fields:
                fields["yaw_deg"] = float(round(rng.uniform(0, 360), 2))
            _, _, reach, height = layout.discs[k]
        else:
            fields, reach, height = _new_object(rng, folder, f"{assets}/o{i}", colours)
        while True:
            try:
                x, y = layout.place(rng, reach, spread)
                break
            except ValueError:
                spread += 0.25  # crowded: widen rather than give up an object
        layout.objects.append({"name": f"o{i}", **fields, "position": [x, y]})
        layout.discs.append((x, y, reach, height))

    radius = max(radius, RADIUS_MARGIN * layout.extent())
    ground_size = float(round(2 * (spread + 1.0) + rng.uniform(2, 8), 2))
    ground: dict[str, Any] = {"size": ground_size}
    if rng.random() < 0.8:
        ground["texture"] = f"{assets}/ground.png"
        _write_png(folder / ground["texture"], ground_texture(rng))
    else:
        ground["color"] = list(_hsv_colour(rng))
    light_r = float(rng.uniform(5, 12))
    light_theta, light_phi = math.radians(rng.uniform(0, 70)), rng.uniform(0, 2 * math.pi)
    light = [
        round(light_r * math.sin(light_theta) * math.cos(light_phi), 3),
        round(light_r * math.sin(light_theta) * math.sin(light_phi), 3),
        round(light_r * math.cos(light_theta), 3),
    ]
    step = float(rng.integers(10, 21)) / 2.0
    data = {
        "camera": {
            "fov_deg": fov,
            "width": width,
            "height": int(round(width / aspect / 2) * 2),
            "radius": float(round(radius, 3)),
        },
        "lighting": {
            "point": {
                "position": light,
                "intensity": float(round(light_r**2 * rng.uniform(1.8, 4.5), 2)),
            },
            "ambient": float(round(rng.uniform(0.05, 0.35), 3)),
        },
        "ground": ground,
        "objects": layout.objects,
        "search": {
            "angle_step_deg": step,
            "min_theta_deg": step,
            "max_theta_deg": math.floor(82.0 / step) * step,
        },
    }
    return write_scene_yaml(folder / f"{scene_id}.yaml", data)


def generate_scenes(count: int, seed: int, folder: Path) -> list[str]:
    """``count`` random scenes of ``seed`` written to ``folder`` (:func:`generate_scene`: the
    ``i``-th ``rand<seed>-<i>``, from a generator seeded ``[seed, i]``); their ids."""
    ids = [f"rand{seed}-{i}" for i in range(count)]
    for i, scene_id in enumerate(ids):
        generate_scene(np.random.default_rng([seed, i]), folder, scene_id)
    return ids


def scene_summary(scene: LoadedScene) -> dict[str, Any]:
    """What a report says about a generated scene: film, fov, radius, grid and its objects."""
    spec = scene.spec
    kinds = []
    for obj in spec.objects:
        kinds.append(
            Path(obj.file).stem.split("-")[-1] if isinstance(obj, MeshObject) else obj.shape
        )
    return {
        "id": scene.id,
        "film": f"{spec.camera.width}x{spec.camera.height}",
        "fov_deg": spec.camera.fov_deg,
        "radius": spec.camera.radius,
        "angle_step_deg": spec.search.angle_step_deg,
        "objects": len(spec.objects),
        "kinds": kinds,
        "ground": "texture" if spec.ground.texture is not None else "colour",
    }
