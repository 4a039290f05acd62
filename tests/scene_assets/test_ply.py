"""The one PLY module (:mod:`scene_assets.ply`): what it writes it reads back, what Mitsuba loads
it reads, and what it cannot read it says so."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from scene_assets import encode_ply, read_ply, read_ply_vertices, write_ply

SCENES_MESHES = ("duck", "arch")


def _mesh(rng: np.random.Generator, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    vertices = rng.normal(size=(n, 3))
    faces = rng.integers(0, n, size=(2 * n, 3))
    return vertices, faces


@pytest.mark.parametrize("attributes", ["none", "normals", "uvs", "both"])
def test_write_then_read_gives_the_mesh_back(tmp_path, attributes):
    rng = np.random.default_rng(7)
    vertices, faces = _mesh(rng)
    normals = rng.normal(size=vertices.shape) if attributes in ("normals", "both") else None
    uvs = rng.random((len(vertices), 2)) if attributes in ("uvs", "both") else None
    path = tmp_path / "deep" / "mesh.ply"
    write_ply(path, vertices, faces, normals=normals, uvs=uvs, comments=["a test"])

    mesh = read_ply(path)
    assert mesh.vertices.dtype == np.float32
    assert mesh.faces.dtype == np.int32
    np.testing.assert_array_equal(mesh.vertices, vertices.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, faces)
    for read, written in ((mesh.normals, normals), (mesh.uvs, uvs)):
        if written is None:
            assert read is None
        else:
            assert read is not None
            np.testing.assert_array_equal(read, written.astype(np.float32))
    np.testing.assert_array_equal(read_ply_vertices(path), mesh.vertices)
    assert path.read_bytes() == encode_ply(
        vertices, faces, normals=normals, uvs=uvs, comments=["a test"]
    )


def test_written_header_is_what_mitsuba_reads():
    data = encode_ply(np.zeros((3, 3)), [[0, 1, 2]], normals=np.ones((3, 3)), uvs=np.zeros((3, 2)))
    header = data[: data.index(b"end_header\n")].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert [line for line in header if line.startswith("property")] == [
        *(f"property float {name}" for name in ("x", "y", "z", "nx", "ny", "nz", "u", "v")),
        "property list uchar int vertex_indices",
    ]


def test_wrong_shapes_are_refused():
    with pytest.raises(ValueError, match="must be"):
        encode_ply(np.zeros((3, 3)), [[0, 1, 2]], normals=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="faces"):
        encode_ply(np.zeros((4, 3)), [[0, 1, 2, 3]])


@pytest.mark.parametrize("name", SCENES_MESHES)
def test_reads_the_committed_meshes_as_mitsuba_loads_them(name):
    mi = pytest.importorskip("mitsuba")
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    from services.common.catalog import BUILTIN_SCENES_DIR

    path = BUILTIN_SCENES_DIR / "meshes" / f"{name}.ply"
    mesh = read_ply(path)
    loaded = mi.load_dict({"type": "ply", "filename": str(path)})
    assert loaded.vertex_count() == len(mesh.vertices)
    assert loaded.face_count() == len(mesh.faces)
    np.testing.assert_array_equal(
        np.array(loaded.vertex_positions_buffer()).reshape(-1, 3), mesh.vertices
    )
    np.testing.assert_array_equal(np.array(loaded.faces_buffer()).reshape(-1, 3), mesh.faces)
    assert mesh.uvs is not None
    np.testing.assert_array_equal(
        np.array(loaded.vertex_texcoords_buffer()).reshape(-1, 2), mesh.uvs
    )


def test_a_written_mesh_loads_in_mitsuba(tmp_path):
    mi = pytest.importorskip("mitsuba")
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    path = tmp_path / "tetra.ply"
    write_ply(path, vertices, faces)
    loaded = mi.load_dict({"type": "ply", "filename": str(path)})
    assert loaded.face_count() == 4
    np.testing.assert_array_equal(np.array(loaded.bbox().max), [1.0, 1.0, 1.0])


@pytest.mark.parametrize("byte_order", ["<", ">", "="])
def test_vertices_are_read_whatever_the_encoding(tmp_path, byte_order):
    """Binary either way round and ASCII, whatever other elements the file holds."""
    xyz = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
    vertex = np.empty(7, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    vertex["red"] = 200
    face = np.empty(1, dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = [0, 1, 2]
    path = tmp_path / "mesh.ply"
    elements = [PlyElement.describe(face, "face"), PlyElement.describe(vertex, "vertex")]
    PlyData(elements, text=byte_order == "=", byte_order=byte_order).write(str(path))
    np.testing.assert_array_equal(read_ply_vertices(path), xyz)
    mesh = read_ply(path)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])
    assert mesh.normals is None
    assert mesh.uvs is None


def test_reader_refuses_what_it_cannot_read(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="not a PLY"):
        read_ply_vertices(bad)
    header = "ply\nformat ascii 1.0\nelement vertex 2\n"
    flat = tmp_path / "flat.ply"
    flat.write_text(header + "property float x\nproperty float y\nend_header\n0 1\n3 4\n")
    with pytest.raises(ValueError, match="no vertex positions"):
        read_ply_vertices(flat)
    lists = tmp_path / "lists.ply"
    lists.write_text(
        header + "property list uchar float x\nproperty float y\nproperty float z\n"
        "end_header\n2 0 1 2 3\n1 4 5 6\n"
    )
    with pytest.raises(ValueError, match="no vertex positions"):
        read_ply_vertices(lists)
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text(
        header + "property float x\nproperty float y\nproperty float z\nend_header\n0 1 2\n3 4 5\n"
    )
    np.testing.assert_array_equal(read_ply_vertices(ascii_ply), [[0, 1, 2], [3, 4, 5]])
    with pytest.raises(ValueError, match="no faces"):
        read_ply(ascii_ply)
    quads = tmp_path / "quads.ply"
    quads.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    with pytest.raises(ValueError, match="not all triangles"):
        read_ply(quads)
