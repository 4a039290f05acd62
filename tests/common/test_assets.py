"""Committed scene assets: reproducible from tools.make_assets, loadable by Mitsuba, well formed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from scene_assets import read_ply
from tools.make_assets import ASSET_PATHS, write_assets

SCENES = Path(__file__).resolve().parents[2] / "scenes"
MESHES = ("duck", "arch")
TEXTURE_SIZES = {"duck": 256, "tiles": 512, "wood": 256}


def _mitsuba() -> Any:
    """Mitsuba with a variant set; keeps whichever variant this process already chose."""
    mi = pytest.importorskip("mitsuba")
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertex table (x y z nx ny nz u v) and triangles."""
    mesh = read_ply(path)
    assert mesh.normals is not None
    assert mesh.uvs is not None
    table = np.concatenate([mesh.vertices, mesh.normals, mesh.uvs], axis=1)
    return table.astype(np.float64), mesh.faces.astype(np.int64)


def test_regenerated_assets_are_byte_identical(tmp_path):
    written = write_assets(tmp_path)
    assert [p.relative_to(tmp_path).as_posix() for p in written] == list(ASSET_PATHS)
    for relative in ASSET_PATHS:
        committed = SCENES / relative
        assert committed.is_file(), f"{relative} missing: run python -m tools.make_assets"
        assert (tmp_path / relative).read_bytes() == committed.read_bytes(), relative
        assert committed.stat().st_size < 300_000


@pytest.mark.parametrize("name", MESHES)
def test_mesh_loads_in_mitsuba_resting_on_ground(name):
    mi = _mitsuba()
    table, faces = _read_ply(SCENES / f"meshes/{name}.ply")
    mesh = mi.load_dict({"type": "ply", "filename": str(SCENES / f"meshes/{name}.ply")})

    assert mesh.face_count() == faces.shape[0]
    assert 300 <= mesh.face_count() <= 2500
    assert mesh.has_vertex_normals()
    assert mesh.has_vertex_texcoords()
    np.testing.assert_allclose(
        np.array(mesh.vertex_texcoords_buffer()).reshape(-1, 2), table[:, 6:8], atol=1e-6
    )

    bbox = mesh.bbox()
    lo, hi = np.array(bbox.min), np.array(bbox.max)
    assert lo[2] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose((lo + hi)[:2] / 2.0, 0.0, atol=1e-5)
    assert 1.5 <= float(np.max(hi - lo)) <= 2.0


@pytest.mark.parametrize("name", MESHES)
def test_mesh_is_closed_with_outward_normals(name):
    table, faces = _read_ply(SCENES / f"meshes/{name}.ply")
    positions, normals, uvs = table[:, :3], table[:, 3:6], table[:, 6:8]

    # Seams and poles duplicate vertices for UVs; weld by position to check topology.
    _, welded = np.unique(np.round(positions, 5), axis=0, return_inverse=True)
    tri = welded.ravel()[faces]
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    directed, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 1), "an edge is used twice in the same direction (bad winding)"
    reverse = {tuple(e) for e in directed[:, ::-1].tolist()}
    assert reverse == {tuple(e) for e in directed.tolist()}, "mesh has boundary edges"

    p = positions[faces]
    face_normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    signed_volume = np.einsum("ij,ij->i", p[:, 0], face_normals).sum() / 6.0
    assert signed_volume > 0.1
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    agreement = np.einsum("ij,ij->i", face_normals, normals[faces].mean(axis=1))
    assert np.all(agreement > 0.0)
    assert uvs.min() >= 0.0
    assert uvs.max() <= 1.0


@pytest.mark.parametrize(("name", "size"), TEXTURE_SIZES.items())
def test_texture_decodes_at_expected_size(name, size):
    image = cv2.imread(str(SCENES / f"textures/{name}.png"), cv2.IMREAD_UNCHANGED)
    assert image is not None
    assert image.shape == (size, size, 3)
    assert image.dtype == np.uint8
    assert image.std() > 2.0


def test_duck_uvs_hit_their_texture_regions():
    table, _ = _read_ply(SCENES / "meshes/duck.ply")
    image = cv2.imread(str(SCENES / "textures/duck.png"))
    assert image is not None
    height, width = image.shape[:2]

    def texel(vertex: int) -> Any:
        # Mitsuba's bitmap texture puts (u, v) = (0, 0) at the top-left pixel.
        u, v = table[vertex, 6:8]
        return image[min(int(v * height), height - 1), min(int(u * width), width - 1)]

    beak_tip = int(np.argmax(table[:, 0]))
    crown = int(np.argmax(table[:, 2]))
    orange_bgr, yellow_bgr = (22, 118, 242), (40, 206, 250)
    np.testing.assert_allclose(texel(beak_tip), orange_bgr, atol=30, err_msg="beak tip")
    np.testing.assert_allclose(texel(crown), yellow_bgr, atol=30, err_msg="top of head")
