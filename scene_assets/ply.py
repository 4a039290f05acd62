"""PLY triangle meshes, read and written with plyfile: the one PLY reader and writer.

Written files are binary little-endian: float32 ``x y z`` (then ``nx ny nz`` and ``u v`` when
given) per vertex and ``vertex_indices`` as ``uchar`` counts of ``int`` indices per face, which is
what Mitsuba's ``ply`` plugin reads. Reading takes ASCII or binary files of either byte order.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from plyfile import PlyData, PlyElement, PlyParseError

__all__ = ["PlyMesh", "encode_ply", "read_ply", "read_ply_vertices", "write_ply"]

_POSITION: tuple[str, ...] = ("x", "y", "z")
_NORMAL: tuple[str, ...] = ("nx", "ny", "nz")
_UV: tuple[str, ...] = ("u", "v")


@dataclass(frozen=True)
class PlyMesh:
    """A triangle mesh as a PLY file holds it.

    Attributes
    ----------
    vertices : (N, 3) float32 positions, scene units.
    faces : (M, 3) int32 vertex indices.
    normals : (N, 3) float32 vertex normals, or None when the file has none.
    uvs : (N, 2) float32 texture coordinates, or None when the file has none.
    """

    vertices: NDArray[np.float32]
    faces: NDArray[np.int32]
    normals: NDArray[np.float32] | None = None
    uvs: NDArray[np.float32] | None = None


def _ply_data(
    vertices: ArrayLike,
    faces: ArrayLike,
    normals: ArrayLike | None,
    uvs: ArrayLike | None,
    comments: Sequence[str],
) -> PlyData:
    columns: list[tuple[tuple[str, ...], NDArray[Any]]] = [(_POSITION, np.asarray(vertices))]
    if normals is not None:
        columns.append((_NORMAL, np.asarray(normals)))
    if uvs is not None:
        columns.append((_UV, np.asarray(uvs)))
    count = len(columns[0][1])
    names = [name for group, _ in columns for name in group]
    vertex = np.empty(count, dtype=[(name, "<f4") for name in names])
    for group, values in columns:
        if values.shape != (count, len(group)):
            shape = (count, len(group))
            raise ValueError(f"{' '.join(group)} must be {shape}, not {values.shape}")
        for k, name in enumerate(group):
            vertex[name] = values[:, k]
    triangles = np.asarray(faces)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"faces must be (M, 3), not {triangles.shape}")
    face = np.empty(len(triangles), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = triangles
    elements = [
        PlyElement.describe(vertex, "vertex"),
        PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"}),
    ]
    return PlyData(elements, text=False, byte_order="<", comments=list(comments))


def encode_ply(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    normals: ArrayLike | None = None,
    uvs: ArrayLike | None = None,
    comments: Sequence[str] = (),
) -> bytes:
    """The bytes of a binary little-endian PLY of the triangles (module docstring).

    Parameters
    ----------
    vertices : (N, 3) positions, stored as float32.
    faces : (M, 3) vertex indices, stored as int32.
    normals : (N, 3) vertex normals, stored as ``nx ny nz``; None writes none.
    uvs : (N, 2) texture coordinates, stored as ``u v``; None writes none.
    comments : header comment lines.
    """
    buffer = io.BytesIO()
    _ply_data(vertices, faces, normals, uvs, comments).write(buffer)
    return buffer.getvalue()


def write_ply(
    path: Path,
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    normals: ArrayLike | None = None,
    uvs: ArrayLike | None = None,
    comments: Sequence[str] = (),
) -> None:
    """Write :func:`encode_ply`'s bytes to ``path``, creating its folder."""
    data = encode_ply(vertices, faces, normals=normals, uvs=uvs, comments=comments)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def _load(path: Path) -> PlyData:
    try:
        return PlyData.read(str(path))
    except PlyParseError as exc:
        raise ValueError(f"{path}: not a PLY file ({exc})") from exc


def _columns(data: PlyData, names: Sequence[str]) -> NDArray[np.float32] | None:
    """The vertex properties ``names`` as float32 columns; None when the file lacks one."""
    try:
        vertex = data["vertex"]
        properties = {p.name for p in vertex.properties}
        if not properties.issuperset(names):
            return None
        return np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=-1)
    except (KeyError, ValueError, TypeError):  # no vertex element, or list properties
        return None


def read_ply_vertices(path: Path) -> NDArray[np.float32]:
    """The ``x, y, z`` of a PLY file's vertices ``(N, 3)`` float32, whatever else it holds.

    Raises
    ------
    ValueError
        The file is not PLY, or has no scalar ``x, y, z`` vertex properties.
    """
    positions = _columns(_load(path), _POSITION)
    if positions is None:
        raise ValueError(f"{path}: no vertex positions")
    return positions


def read_ply(path: Path) -> PlyMesh:
    """The triangle mesh of a PLY file (:class:`PlyMesh`): positions, triangles, and normals and
    texture coordinates where the file has them.

    Raises
    ------
    ValueError
        The file is not PLY, has no scalar ``x, y, z`` vertex properties, or its faces are not
        triangles.
    """
    data = _load(path)
    positions = _columns(data, _POSITION)
    if positions is None:
        raise ValueError(f"{path}: no vertex positions")
    try:
        lists = data["face"]["vertex_indices"]
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: no faces") from exc
    try:
        faces = np.asarray(np.stack(list(lists)), dtype=np.int32).reshape(len(lists), -1)
    except ValueError as exc:  # faces of different lengths
        raise ValueError(f"{path}: faces are not all triangles") from exc
    if faces.shape[1] != 3:
        raise ValueError(f"{path}: faces are not all triangles")
    return PlyMesh(positions, faces, _columns(data, _NORMAL), _columns(data, _UV))
