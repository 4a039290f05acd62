"""Translate a validated scene spec into Mitsuba 3 scene dictionaries.

Runs on the render worker thread after the Mitsuba variant is set. Every Mitsuba shape an object
contributes gets an id ``obj<index>`` or ``obj<index>_<part>`` so per-pixel shape ids can be mapped
back to scene objects; the ground is ``ground``.

Placement (world z up, ground z = 0, ``position`` = footprint centre):

* sphere: centre ``(x, y, r)``;
* cube: Mitsuba's cube spans [-1, 1]³, so ``T(x, y, s/2) · Rz(yaw) · S(s/2)``;
* cylinder: Mitsuba's cylinder is open, so an upright tube from z = 0 to h plus a disk cap at h;
* cone: a triangle mesh built here (side fan and base disk);
* mesh: the PLY's bounding box is measured once, then ``T(x, y, 0) · Rz(yaw) · S(scale) · T(-c)``
  where c is the bottom centre of that box, so every mesh rests on the ground at its position.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from services.common.geometry.camera import PinholeCamera, mitsuba_to_world
from services.common.geometry.pose import Pose
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    LoadedScene,
    MeshObject,
    SceneObject,
    SphereObject,
)
from services.renderer.variant import SCALAR_VARIANT

__all__ = [
    "CONE_SEGMENTS",
    "MASK_SENSOR",
    "RGB_SENSOR",
    "build_object_scene",
    "build_scene",
    "object_index_of",
    "object_centroid",
    "place_sensor",
    "shape_keys",
]

RGB_SENSOR = 0
MASK_SENSOR = 1
CONE_SEGMENTS = 64
_INITIAL_POSE = Pose(theta_deg=45.0, phi_deg=0.0)


def object_index_of(shape_id: str) -> int:
    """The object index encoded in a shape id (``obj3`` or ``obj3_cap`` -> 3); -1 otherwise."""
    if not shape_id.startswith("obj"):
        return -1
    head = shape_id[3:].split("_", 1)[0]
    return int(head) if head.isdigit() else -1


def _appearance(
    mi: Any, scene: LoadedScene, field: str, color: Any, texture: Any
) -> dict[str, Any]:
    if texture is not None:
        reflectance: dict[str, Any] = {
            "type": "bitmap",
            "filename": str(scene.assets[f"{field}.texture"]),
            "wrap_mode": "clamp",
        }
    else:
        rgb = color if color is not None else (0.5, 0.5, 0.5)
        reflectance = {"type": "rgb", "value": [float(c) for c in rgb]}
    return {"type": "diffuse", "reflectance": reflectance}


def _sensor(mi: Any, fov_deg: float, width: int, height: int, mask: bool) -> dict[str, Any]:
    sampler: dict[str, Any] = (
        {"type": "stratified", "sample_count": 1, "jitter": False}
        if mask
        else {"type": "independent", "sample_count": 4}
    )
    return {
        "type": "perspective",
        "fov": float(fov_deg),
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 1e4,
        "to_world": mi.ScalarTransform4f(mitsuba_to_world(_INITIAL_POSE, 10.0).tolist()),
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": sampler,
    }


def _yaw(obj: SceneObject) -> float:
    return float(getattr(obj, "yaw_deg", 0.0))


def _cone_mesh(mi: Any, name: str, obj: ConeObject, bsdf: dict[str, Any]) -> Any:
    """A closed cone: ``CONE_SEGMENTS`` side triangles to the apex and a base fan, UV-mapped."""
    n = CONE_SEGMENTS
    angles = np.linspace(0.0, 2.0 * math.pi, n + 1) + math.radians(obj.yaw_deg)
    x0, y0 = obj.position
    ring = np.stack(
        [x0 + obj.radius * np.cos(angles), y0 + obj.radius * np.sin(angles), np.zeros(n + 1)],
        axis=1,
    )
    apex = np.tile([x0, y0, obj.height], (n, 1))
    centre = np.array([[x0, y0, 0.0]])
    base_ring = ring[:n]
    vertices = np.concatenate([ring, apex, centre, base_ring]).astype(np.float32)
    u_ring = np.linspace(0.0, 1.0, n + 1)
    uv = np.concatenate(
        [
            np.stack([u_ring, np.zeros(n + 1)], axis=1),
            np.stack([(np.arange(n) + 0.5) / n, np.ones(n)], axis=1),
            [[0.5, 0.5]],
            np.stack([0.5 + 0.5 * np.cos(angles[:n]), 0.5 + 0.5 * np.sin(angles[:n])], axis=1),
        ]
    ).astype(np.float32)
    i = np.arange(n)
    apex0, centre_i, base0 = n + 1, 2 * n + 1, 2 * n + 2
    side = np.stack([i, i + 1, apex0 + i], axis=1)
    base = np.stack([np.full(n, centre_i), base0 + (i + 1) % n, base0 + i], axis=1)
    faces = np.concatenate([side, base]).astype(np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(
        name,
        vertex_count=len(vertices),
        face_count=len(faces),
        props=props,
        has_vertex_normals=False,
        has_vertex_texcoords=True,
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = type(params["vertex_positions"])(vertices.ravel())
    params["vertex_texcoords"] = type(params["vertex_texcoords"])(uv.ravel())
    params["faces"] = type(params["faces"])(faces.ravel())
    params.update()
    return mesh


def _mesh_transform(mi: Any, scene: LoadedScene, index: int, obj: MeshObject) -> Any:
    path = str(scene.assets[f"objects[{index}].file"])
    bbox = mi.load_dict({"type": "ply", "filename": path}).bbox()
    lo, hi = np.array(bbox.min, dtype=np.float64), np.array(bbox.max, dtype=np.float64)
    bottom_centre = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]]
    x, y = obj.position
    return (
        mi.ScalarTransform4f()
        .translate([x, y, 0.0])
        .rotate([0.0, 0.0, 1.0], obj.yaw_deg)
        .scale(obj.scale)
        .translate([-c for c in bottom_centre])
    )


def _object_shapes(mi: Any, scene: LoadedScene, index: int) -> dict[str, Any]:
    """The Mitsuba shapes making up object ``index``, keyed by shape id."""
    obj = scene.spec.objects[index]
    name = f"obj{index}"
    bsdf = _appearance(mi, scene, f"objects[{index}]", obj.color, obj.texture)
    x, y = obj.position
    T = mi.ScalarTransform4f
    if isinstance(obj, SphereObject):
        return {
            name: {
                "type": "sphere",
                "center": [x, y, obj.radius],
                "radius": obj.radius,
                "bsdf": bsdf,
            }
        }
    if isinstance(obj, CubeObject):
        half = obj.size / 2.0
        to_world = T().translate([x, y, half]).rotate([0.0, 0.0, 1.0], obj.yaw_deg).scale(half)
        return {name: {"type": "cube", "to_world": to_world, "bsdf": bsdf}}
    if isinstance(obj, CylinderObject):
        tube = T().translate([x, y, 0.0]).rotate([0.0, 0.0, 1.0], obj.yaw_deg)
        tube = tube.scale([obj.radius, obj.radius, obj.height])
        cap = (
            T().translate([x, y, obj.height]).rotate([0.0, 0.0, 1.0], obj.yaw_deg).scale(obj.radius)
        )
        return {
            name: {"type": "cylinder", "to_world": tube, "bsdf": bsdf},
            f"{name}_cap": {"type": "disk", "to_world": cap, "bsdf": bsdf},
        }
    if isinstance(obj, ConeObject):
        return {name: _cone_mesh(mi, name, obj, bsdf)}
    return {
        name: {
            "type": "ply",
            "filename": str(scene.assets[f"objects[{index}].file"]),
            "to_world": _mesh_transform(mi, scene, index, obj),
            "face_normals": False,
            "bsdf": bsdf,
        }
    }


def object_centroid(obj: SceneObject) -> tuple[float, float, float]:
    """World centre of a primitive's bounding box (meshes: measured by the engine instead)."""
    x, y = obj.position
    if isinstance(obj, SphereObject):
        return (x, y, obj.radius)
    if isinstance(obj, CubeObject):
        return (x, y, obj.size / 2.0)
    if isinstance(obj, CylinderObject | ConeObject):
        return (x, y, obj.height / 2.0)
    raise TypeError("mesh centroids are measured from the loaded mesh")


def build_scene(mi: Any, scene: LoadedScene, width: int, height: int) -> dict[str, Any]:
    """The whole scene: RGB and mask sensors, point emitter and ambient light, ground, objects."""
    spec = scene.spec
    half = spec.ground.size / 2.0
    data: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "camera": _sensor(mi, spec.camera.fov_deg, width, height, mask=False),
        "mask_camera": _sensor(mi, spec.camera.fov_deg, width, height, mask=True),
        "light": {
            "type": "point",
            "position": [float(v) for v in spec.lighting.point.position],
            "intensity": {"type": "rgb", "value": float(spec.lighting.point.intensity)},
        },
        "ground": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().scale([half, half, 1.0]),
            "bsdf": _appearance(mi, scene, "ground", spec.ground.color, spec.ground.texture),
        },
    }
    if spec.lighting.ambient > 0.0:
        data["ambient"] = {
            "type": "constant",
            "radiance": {"type": "rgb", "value": float(spec.lighting.ambient)},
        }
    for index in range(len(spec.objects)):
        data.update(_object_shapes(mi, scene, index))
    return data


def build_object_scene(
    mi: Any, scene: LoadedScene, index: int, width: int, height: int
) -> dict[str, Any]:
    """Object ``index`` alone in front of the mask sensor: its unoccluded silhouette."""
    data: dict[str, Any] = {
        "type": "scene",
        "mask_camera": _sensor(mi, scene.spec.camera.fov_deg, width, height, mask=True),
    }
    data.update(_object_shapes(mi, scene, index))
    return data


def shape_keys(mi: Any, dr: Any, variant: str, shapes: list[Any]) -> list[int]:
    """The value the ``shape_index`` AOV reports for each shape.

    Scalar variants report the 1-based position in ``scene.shapes()``; JIT variants report the
    shape's id in Dr.Jit's instance registry (what ``ShapePtr`` holds), which counts every shape
    the process ever created.
    """
    if variant == SCALAR_VARIANT:
        return list(range(1, len(shapes) + 1))
    return [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]) for shape in shapes]


def place_sensor(mi: Any, params: Any, sensor: str, camera: PinholeCamera) -> None:
    """Point the sensor of ``params`` at ``camera``: Mitsuba's camera space is x left, y up,
    z forward, so its camera-to-world columns are ``(-right, -down, forward, position)``; its
    principal point sits at ``(0.5 - o_x) W, (0.5 - o_y) H`` for offsets ``o``."""
    rotation = np.asarray(camera.rotation)
    matrix = np.eye(4)
    matrix[:3, 0] = -rotation[0]
    matrix[:3, 1] = -rotation[1]
    matrix[:3, 2] = rotation[2]
    matrix[:3, 3] = camera.position
    params[f"{sensor}.to_world"] = mi.ScalarTransform4f(matrix.tolist())
    params[f"{sensor}.x_fov"] = camera.fov_deg
    params[f"{sensor}.principal_point_offset_x"] = 0.5 - camera.cx / camera.width
    params[f"{sensor}.principal_point_offset_y"] = 0.5 - camera.cy / camera.height
    params.update()
