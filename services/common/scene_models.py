"""A scene's own detector: its classes (one per object, look-alikes shared) and where it lives.

Onboarding a scene (``cosmos scenes add``) trains a detector whose classes are the scene's
objects, not shape types. Objects that look alike — same shape, same dimensions, same colour or
texture, like two identical bales — cannot be told apart by their looks, so they share one class;
geometry tells them apart during matching. Yaw is not part of the look: a turned copy of an
object is still the same object to a detector.

A class's label is its object's ``name``; a shared class is labelled with its members' names
joined by ``+`` (``bale1+bale2``), which no object name can be (names allow ``[A-Za-z0-9_-]``),
shortened to ``first+N`` when that would exceed the 64 characters of a detection label.

The model of scene ``<dir>/<id>.yaml`` lies beside it, in ``<dir>/<id>.detector/``:
``model.onnx``, its sidecar ``model.json`` (classes, sha256, provenance) and ``MODEL_CARD.md``.
Onboarding writes the sidecar first and moves the ONNX file into place last, atomically; a
reader trusts a model only when the sidecar's sha256 is the file's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Final, Literal

from pydantic import Field

from services.common.base import FrozenModel
from services.common.geometry.scene import (
    ConeObject,
    CubeObject,
    CylinderObject,
    LoadedScene,
    MeshObject,
    SceneObject,
    SceneSpec,
    SphereObject,
)

__all__ = [
    "MAX_LABEL_CHARS",
    "MODEL_CARD_NAME",
    "MODEL_DIR_SUFFIX",
    "MODEL_FILE_NAME",
    "SIDECAR_NAME",
    "ObjectClass",
    "Shape",
    "class_label",
    "look_key",
    "model_dir",
    "object_classes",
]

Shape = Literal["sphere", "cube", "cylinder", "cone", "mesh"]

MAX_LABEL_CHARS: Final = 64
MODEL_DIR_SUFFIX: Final = ".detector"
MODEL_FILE_NAME: Final = "model.onnx"
SIDECAR_NAME: Final = "model.json"
MODEL_CARD_NAME: Final = "MODEL_CARD.md"

_SIZE_TOLERANCE: Final = 0.02
"""Relative difference of dimensions below which two objects are the same size."""
_COLOUR_TOLERANCE: Final = 0.03
"""Linear-RGB distance below which two colours are the same."""


class ObjectClass(FrozenModel):
    """One class of a scene's own detector: the objects it stands for and their shape."""

    label: Annotated[str, Field(min_length=1, max_length=MAX_LABEL_CHARS)]
    shape: Shape
    objects: Annotated[tuple[str, ...], Field(min_length=1, max_length=64)]


def look_key(obj: SceneObject) -> tuple[object, ...]:
    """The part of an object's look that must be equal for two objects to be alike (colours
    and dimensions are compared with tolerances by :func:`object_classes`)."""
    if isinstance(obj, MeshObject):
        return (obj.shape, obj.file, obj.texture)
    return (obj.shape, obj.texture)


def _dimensions(obj: SceneObject) -> tuple[float, ...]:
    if isinstance(obj, SphereObject):
        return (obj.radius,)
    if isinstance(obj, CubeObject):
        return (obj.size,)
    if isinstance(obj, CylinderObject | ConeObject):
        return (obj.radius, obj.height)
    return (obj.scale,)


def _alike(a: SceneObject, b: SceneObject) -> bool:
    """Same shape, dimensions within 2 %, and the same texture or colours within 0.03."""
    if look_key(a) != look_key(b):
        return False
    for x, y in zip(_dimensions(a), _dimensions(b), strict=True):
        if abs(x - y) > _SIZE_TOLERANCE * max(x, y):
            return False
    if a.color is None or b.color is None:
        return a.color is None and b.color is None
    return math.dist(a.color, b.color) <= _COLOUR_TOLERANCE


def class_label(names: Sequence[str]) -> str:
    """The label of a class standing for the objects ``names`` (module docstring)."""
    if len(names) == 1:
        return names[0]
    joined = "+".join(names)
    if len(joined) <= MAX_LABEL_CHARS:
        return joined
    suffix = f"+{len(names) - 1}"
    return names[0][: MAX_LABEL_CHARS - len(suffix)] + suffix


def object_classes(spec: SceneSpec) -> tuple[ObjectClass, ...]:
    """The classes of ``spec``'s own detector, in the order of each class's first object.

    Look-alike is taken transitively: if a is like b and b like c, all three share a class.
    """
    objects = spec.objects
    group = list(range(len(objects)))  # union-find over objects

    def root(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    for i in range(len(objects)):
        for j in range(i + 1, len(objects)):
            if _alike(objects[i], objects[j]):
                group[root(j)] = root(i)
    members: dict[int, list[int]] = {}
    for i in range(len(objects)):
        members.setdefault(root(i), []).append(i)
    return tuple(
        ObjectClass(
            label=class_label([objects[i].name for i in idx]),
            shape=objects[idx[0]].shape,
            objects=tuple(objects[i].name for i in idx),
        )
        for idx in sorted(members.values(), key=lambda m: m[0])
    )


def model_dir(scene: LoadedScene | Path) -> Path:
    """The folder holding the scene's own detector (it may not exist yet)."""
    path = scene.path if isinstance(scene, LoadedScene) else scene
    return path.parent / f"{path.stem}{MODEL_DIR_SUFFIX}"
