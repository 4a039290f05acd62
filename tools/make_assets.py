"""Generate the built-in scene assets: low-poly PLY meshes and procedural PNG textures.

Run ``python -m tools.make_assets [--out scenes]``. Output is deterministic: the same bytes on
every run (fixed geometry, seeded RNG, fixed PNG parameters), so the committed files under
``scenes/`` can be checked against a fresh build.

Conventions
-----------
Meshes are z-up, rest on z = 0 and are centred on the z axis (bounding-box centre at x = y = 0),
lengths in scene units at ``scale`` 1. PLY vertices carry ``x y z nx ny nz u v`` (float32,
binary little-endian), faces are ``vertex_indices`` triangles wound counter-clockwise seen from
outside. Mitsuba's ``ply`` plugin reads ``u, v`` as-is and its ``bitmap`` texture maps
(u, v) = (0, 0) to the top-left pixel of the PNG: pixel column = u * width, row = v * height.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "ASSET_PATHS",
    "Mesh",
    "arch_mesh",
    "build_assets",
    "duck_mesh",
    "duck_texture",
    "encode_ply",
    "encode_png",
    "main",
    "tiles_texture",
    "wood_texture",
    "write_assets",
]

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]
Image = NDArray[np.uint8]

ASSET_PATHS: tuple[str, ...] = (
    "meshes/duck.ply",
    "meshes/arch.ply",
    "textures/duck.png",
    "textures/tiles.png",
    "textures/wood.png",
)
"""Files written by :func:`write_assets`, relative to the output folder."""

_DEFAULT_OUT = Path(__file__).resolve().parents[1] / "scenes"
_SEED = 20240611
_PNG_PARAMS = (cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, 0)
_WELD_SCALE = 1e6  # positions equal to 1e-6 units share one smoothed normal

# Duck texture atlas, as (u0, v0, u1, v1) boxes in texture space (v = 0 is the top row).
_BODY_UV = (0.0, 0.0, 1.0, 0.5)
_HEAD_UV = (0.0, 0.5, 1.0, 0.875)
_TRIM_UV = (0.0, 0.875, 0.5, 1.0)  # tail and wings
_BEAK_UV = (0.5, 0.875, 1.0, 1.0)
_UV_INSET = 2.0 / 256.0  # keeps bilinear lookups from bleeding across atlas boxes


@dataclass(frozen=True)
class Mesh:
    """Triangle mesh with per-vertex attributes.

    Attributes
    ----------
    positions : (N, 3) float64, scene units, z up.
    normals : (N, 3) float64, unit length, pointing out of the solid.
    uvs : (N, 2) float64 texture coordinates in [0, 1].
    faces : (M, 3) int64 vertex indices, counter-clockwise seen from outside.
    """

    positions: FloatArray
    normals: FloatArray
    uvs: FloatArray
    faces: IndexArray


@dataclass(frozen=True)
class _Part:
    """Mesh piece before normals: one closed shell or one surface of a shell."""

    positions: FloatArray
    uvs: FloatArray
    faces: IndexArray


def _rotation_y(angle_rad: float) -> FloatArray:
    """Rotation matrix about +y; positive angles tip +x towards -z."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _uv_in_box(s: FloatArray, t: FloatArray, box: tuple[float, float, float, float]) -> FloatArray:
    """Map unit-square coordinates ``(s, t)`` into an atlas box, inset from its border."""
    u0, v0, u1, v1 = box
    u = u0 + _UV_INSET + s * (u1 - u0 - 2.0 * _UV_INSET)
    v = v0 + _UV_INSET + t * (v1 - v0 - 2.0 * _UV_INSET)
    return np.stack([u, v], axis=-1)


def _grid_faces(rows: int, cols: int) -> IndexArray:
    """Two triangles per cell of a ``rows`` x ``cols`` vertex grid (row-major indices)."""
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (i * cols + j).ravel()
    b = a + cols
    c = b + 1
    d = a + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)


def _drop_degenerate(positions: FloatArray, faces: IndexArray) -> IndexArray:
    """Remove zero-area triangles (the collapsed cells at poles and flattened caps)."""
    p = positions[faces]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    kept: IndexArray = faces[area2 > 1e-12]
    return kept


def _ellipsoid(
    center: Sequence[float],
    radii: Sequence[float],
    n_around: int,
    n_rings: int,
    uv_box: tuple[float, float, float, float],
    rotation: FloatArray | None = None,
    z_floor: float | None = None,
) -> _Part:
    """Closed latitude-longitude ellipsoid.

    A vertex at polar angle theta (from the local +z) and azimuth phi (from the local +x) sits
    at ``center + R @ (radii * (sin theta cos phi, sin theta sin phi, cos theta))``, with
    texture coordinates (phi / 2 pi, theta / pi) inside ``uv_box``. Vertices below ``z_floor``
    are pressed onto that plane, which gives the shell a flat base.
    """
    theta = np.linspace(0.0, np.pi, n_rings + 1)
    phi = np.linspace(0.0, 2.0 * np.pi, n_around + 1)
    st, ct = np.sin(theta), np.cos(theta)
    sp, cp = np.sin(phi), np.cos(phi)
    # Exact pole and seam values, so duplicated vertices coincide and share one normal.
    st[[0, -1]], ct[[0, -1]] = 0.0, [1.0, -1.0]
    sp[-1], cp[-1] = sp[0], cp[0]
    unit = np.stack(
        [st[:, None] * cp[None, :], st[:, None] * sp[None, :], np.repeat(ct[:, None], phi.size, 1)],
        axis=-1,
    ).reshape(-1, 3)
    local = unit * np.asarray(radii, dtype=np.float64)
    if rotation is not None:
        local = local @ rotation.T
    positions = local + np.asarray(center, dtype=np.float64)
    if z_floor is not None:
        positions[:, 2] = np.maximum(positions[:, 2], z_floor)
    s, t = np.meshgrid(phi / (2.0 * np.pi), theta / np.pi)
    uvs = _uv_in_box(s.ravel(), t.ravel(), uv_box)
    faces = _drop_degenerate(positions, _grid_faces(n_rings + 1, n_around + 1))
    return _Part(positions, uvs, faces)


def _smooth_normals(part: _Part) -> FloatArray:
    """Area-weighted vertex normals, shared by all vertices at one position (seams, poles)."""
    p = part.positions[part.faces]
    face_normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 * area
    keys = np.round(part.positions * _WELD_SCALE).astype(np.int64)
    _, welded = np.unique(keys, axis=0, return_inverse=True)
    welded = welded.ravel()
    accum = np.zeros((int(welded.max()) + 1, 3))
    for corner in range(3):
        np.add.at(accum, welded[part.faces[:, corner]], face_normals)
    normals = accum[welded]
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(lengths == 0.0):
        raise ValueError("mesh has vertices without any adjacent non-degenerate face")
    result: FloatArray = normals / lengths
    return result


def _assemble(parts: Sequence[_Part], normals: Sequence[FloatArray]) -> Mesh:
    """Concatenate parts, then translate so the bbox is centred on the z axis with min z = 0."""
    offsets = np.cumsum([0] + [part.positions.shape[0] for part in parts[:-1]])
    positions = np.concatenate([part.positions for part in parts])
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    shift = np.array([-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])
    return Mesh(
        positions=positions + shift,
        normals=np.concatenate(list(normals)),
        uvs=np.concatenate([part.uvs for part in parts]),
        faces=np.concatenate(
            [part.faces + offset for part, offset in zip(parts, offsets, strict=True)]
        ),
    )


def duck_mesh() -> Mesh:
    """Low-poly rubber duck facing +x, about 1.8 x 1.1 x 1.3 units (~1.8k triangles).

    Five overlapping closed shells: an ellipsoid body with a flat base, a sphere-like head, a
    flattened beak, an upturned tail and two side wings. UVs follow the duck texture atlas.
    """
    parts = [
        _ellipsoid((0.0, 0.0, 0.42), (0.72, 0.52, 0.42), 28, 14, _BODY_UV, z_floor=0.06),
        _ellipsoid((0.38, 0.0, 0.98), (0.34, 0.32, 0.33), 24, 12, _HEAD_UV),
        _ellipsoid((0.74, 0.0, 0.92), (0.17, 0.14, 0.055), 16, 8, _BEAK_UV, _rotation_y(0.15)),
        _ellipsoid((-0.66, 0.0, 0.6), (0.24, 0.17, 0.1), 12, 6, _TRIM_UV, _rotation_y(0.7)),
    ]
    for side in (-1.0, 1.0):
        wing = (-0.06, side * 0.46, 0.5)
        parts.append(_ellipsoid(wing, (0.34, 0.1, 0.18), 12, 6, _TRIM_UV, _rotation_y(0.25)))
    return _assemble(parts, [_smooth_normals(part) for part in parts])


def _arch_centerline(t: FloatArray, half_span: float, rise: float) -> FloatArray:
    """Half-ellipse ``(half_span cos t, 0, rise sin t)``, t in [0, pi]; both feet on z = 0."""
    return np.stack([half_span * np.cos(t), np.zeros_like(t), rise * np.sin(t)], axis=-1)


def _orient_away_from(part: _Part, inner: FloatArray) -> _Part:
    """Flip the winding if face normals point towards the per-vertex ``inner`` points."""
    p = part.positions[part.faces]
    face_normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    away = p.mean(axis=1) - inner[part.faces].mean(axis=1)
    if float(np.sum(face_normals * away)) >= 0.0:
        return part
    return _Part(part.positions, part.uvs, part.faces[:, ::-1].copy())


def _floor_cap(
    ring: FloatArray, center: FloatArray, across: FloatArray, through: FloatArray
) -> _Part:
    """Triangle fan closing a ring on z = 0, wound to face -z (down into the ground)."""
    n = ring.shape[0]
    positions = np.concatenate([center[None, :], ring])
    span = 2.0 * max(float(np.abs(across).max()), float(np.abs(through).max()))
    local = np.concatenate([[[0.0, 0.0]], np.stack([across, through], -1)]) / span
    uvs = 0.5 + 0.25 * local
    j = np.arange(n)
    faces = np.stack([np.zeros(n, dtype=np.int64), 1 + j, 1 + (j + 1) % n], 1)
    tri = positions[faces]
    if float(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2].sum()) > 0.0:
        faces = faces[:, ::-1].copy()
    return _Part(positions, uvs, faces.astype(np.int64))


def arch_mesh() -> Mesh:
    """Low-poly arch: a rounded-rectangle tube swept over a half ellipse, about 1.74 x 0.4 x 1.0.

    The tube's cross-section is the superellipse ``|y / w|^4 + |n / h|^4 = 1`` (half-width
    w along y, half-thickness h along the in-plane normal n of the centreline); the ends are flat
    caps lying on z = 0. u runs along the arch from the +x foot (u = 0) to the -x foot (u = 1),
    v around the cross-section; the caps map to a small patch in the middle of the texture.
    """
    half_span, rise, half_width, half_thick = 0.75, 0.85, 0.2, 0.12
    n_along, n_around = 24, 16
    t = np.linspace(0.0, np.pi, n_along + 1)
    s = np.linspace(0.0, 2.0 * np.pi, n_around + 1)
    cs, ss = np.cos(s), np.sin(s)
    cs[-1], ss[-1] = cs[0], ss[0]
    across = np.sign(cs) * np.abs(cs) ** 0.5 * half_width
    through = np.sign(ss) * np.abs(ss) ** 0.5 * half_thick

    center = _arch_centerline(t, half_span, rise)
    center[[0, -1], 2] = 0.0
    tangent = np.stack([-half_span * np.sin(t), np.zeros_like(t), rise * np.cos(t)], axis=-1)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    outward = np.stack([tangent[:, 2], np.zeros_like(t), -tangent[:, 0]], axis=-1)
    # The feet are exactly vertical, so the end rings lie exactly on z = 0.
    outward[[0, -1]] = [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]
    y_axis = np.array([0.0, 1.0, 0.0])
    rings = (
        center[:, None, :]
        + across[None, :, None] * y_axis[None, None, :]
        + through[None, :, None] * outward[:, None, :]
    )
    su, sv = np.meshgrid(s / (2.0 * np.pi), t / np.pi)
    faces = _grid_faces(n_along + 1, n_around + 1)
    tube = _Part(rings.reshape(-1, 3), np.stack([sv.ravel(), su.ravel()], -1), faces)
    tube = _orient_away_from(tube, np.repeat(center, n_around + 1, axis=0))

    parts, normals = [tube], [_smooth_normals(tube)]
    for end in (0, n_along):
        cap = _floor_cap(rings[end, :-1], center[end], across[:-1], through[:-1])
        parts.append(cap)
        normals.append(np.tile([0.0, 0.0, -1.0], (cap.positions.shape[0], 1)))
    return _assemble(parts, normals)


def encode_ply(mesh: Mesh) -> bytes:
    """Binary little-endian PLY with float32 ``x y z nx ny nz u v`` and int32 triangles."""
    names = ("x", "y", "z", "nx", "ny", "nz", "u", "v")
    n_vertices, n_faces = mesh.positions.shape[0], mesh.faces.shape[0]
    header = "".join(
        [
            "ply\n",
            "format binary_little_endian 1.0\n",
            "comment generated by tools.make_assets (COSMOS 3D Search)\n",
            f"element vertex {n_vertices}\n",
            *(f"property float {name}\n" for name in names),
            f"element face {n_faces}\n",
            "property list uchar int vertex_indices\n",
            "end_header\n",
        ]
    )
    vertices = np.concatenate([mesh.positions, mesh.normals, mesh.uvs], axis=1).astype("<f4")
    faces = np.zeros(n_faces, dtype=[("count", "u1"), ("indices", "<i4", (3,))])
    faces["count"] = 3
    faces["indices"] = mesh.faces
    return header.encode("ascii") + vertices.tobytes() + faces.tobytes()


def encode_png(image: Image) -> bytes:
    """PNG bytes of a BGR uint8 image with fixed encoder settings."""
    ok, buffer = cv2.imencode(".png", image, list(_PNG_PARAMS))
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(buffer.tobytes())


def _bgr(rgb: Sequence[int]) -> tuple[int, int, int]:
    """OpenCV colour tuple from an RGB triple."""
    return int(rgb[2]), int(rgb[1]), int(rgb[0])


def _fill_box(image: Image, box: tuple[float, float, float, float], rgb: Sequence[int]) -> None:
    """Paint an atlas box (u0, v0, u1, v1) with a flat colour."""
    height, width = image.shape[:2]
    u0, v0, u1, v1 = box
    rows = slice(round(v0 * height), round(v1 * height))
    image[rows, round(u0 * width) : round(u1 * width)] = _bgr(rgb)


def duck_texture(size: int = 256) -> Image:
    """Duck UV atlas (BGR): yellow body and head with two eyes, deeper yellow trim, orange beak.

    Eyes sit on the head's lat-long map at azimuth phi = +-0.6 rad from the beak and polar
    angle theta = 1.1 rad, drawn as ellipses stretched by 1 / sin(theta) along u so they
    look round on the sphere.
    """
    image = np.zeros((size, size, 3), dtype=np.uint8)
    _fill_box(image, _BODY_UV, (250, 206, 40))
    _fill_box(image, _HEAD_UV, (250, 206, 40))
    _fill_box(image, _TRIM_UV, (238, 184, 24))
    _fill_box(image, _BEAK_UV, (242, 118, 22))
    u0, v0, u1, v1 = _HEAD_UV
    theta, eye_rad = 1.1, 0.16
    row = (v0 + (v1 - v0) * theta / np.pi) * size
    half_h = (v1 - v0) * eye_rad / np.pi * size
    half_w = eye_rad / np.sin(theta) / (2.0 * np.pi) * (u1 - u0) * size
    for phi in (0.6, 2.0 * np.pi - 0.6):
        col = (u0 + (u1 - u0) * phi / (2.0 * np.pi)) * size
        center = (round(col), round(row))
        axes = (round(half_w), round(half_h))
        cv2.ellipse(image, center, axes, 0.0, 0.0, 360.0, _bgr((24, 20, 16)), -1, cv2.LINE_AA)
        glint = (round(col + 0.3 * half_w), round(row - 0.35 * half_h))
        glint_axes = (max(1, round(0.3 * half_w)), max(1, round(0.3 * half_h)))
        cv2.ellipse(image, glint, glint_axes, 0.0, 0.0, 360.0, _bgr((245, 245, 245)), -1)
    return image


def _smooth_noise(
    rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]
) -> FloatArray:
    """Value noise in [-1, 1]: a ``cells`` grid of uniform samples, bicubically upsampled."""
    coarse = rng.uniform(-1.0, 1.0, size=cells).astype(np.float32)
    fine = cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return np.clip(fine.astype(np.float64), -1.0, 1.0)


def _to_image(rgb: FloatArray) -> Image:
    """BGR uint8 image from an (H, W, 3) RGB array of 0-255 values."""
    image: Image = np.clip(np.rint(rgb[..., ::-1]), 0, 255).astype(np.uint8)
    return image


def tiles_texture(size: int = 512, tiles: int = 8, grout_px: int = 4) -> Image:
    """Muted grey floor tiles (BGR): a ``tiles`` x ``tiles`` checker with grout lines.

    Every tile gets its own small brightness offset and a faint mottle, so the pattern is not
    perfectly periodic (helps tell one ground position from another).
    """
    rng = np.random.default_rng(_SEED)
    tile_px = size // tiles
    rows, cols = np.mgrid[0:size, 0:size]
    ti, tj = rows // tile_px, cols // tile_px
    light = np.array([178.0, 174.0, 164.0])
    dark = np.array([128.0, 126.0, 120.0])
    base = np.where(((ti + tj) % 2 == 0)[..., None], light, dark)
    offsets = rng.uniform(-9.0, 9.0, size=(tiles, tiles))
    mottle = 4.0 * _smooth_noise(rng, (size, size), (tiles * 4, tiles * 4))
    rgb = base + (offsets[ti, tj] + mottle)[..., None]
    half = grout_px // 2
    in_grout = ((rows + half) % tile_px < grout_px) | ((cols + half) % tile_px < grout_px)
    rgb[in_grout] = [96.0, 94.0, 90.0]
    return _to_image(rgb)


def wood_texture(size: int = 256) -> Image:
    """Procedural wood grain (BGR) with the grain running along u (image rows).

    Growth rings are ``frac(k * (y + a * warp(x, y)))`` over the row coordinate y, bent by
    smooth noise, darkened towards each ring's late wood, plus fine fibre streaks along x.
    """
    rng = np.random.default_rng(_SEED + 1)
    y = np.linspace(0.0, 1.0, size, endpoint=False)[:, None] * np.ones((1, size))
    warp = _smooth_noise(rng, (size, size), (6, 4))
    rings = (9.0 * (y + 0.06 * warp)) % 1.0
    late_wood = np.clip((rings - 0.55) / 0.45, 0.0, 1.0) ** 1.5
    fibres = _smooth_noise(rng, (size, size), (96, 6))
    tone = np.clip(0.75 * late_wood + 0.12 * fibres + 0.05, 0.0, 1.0)
    light = np.array([206.0, 160.0, 108.0])
    dark = np.array([134.0, 88.0, 50.0])
    return _to_image(light + tone[..., None] * (dark - light))


def build_assets() -> dict[str, bytes]:
    """All asset files as ``{relative path: bytes}``, in :data:`ASSET_PATHS` order."""
    builders: dict[str, Callable[[], bytes]] = {
        "meshes/duck.ply": lambda: encode_ply(duck_mesh()),
        "meshes/arch.ply": lambda: encode_ply(arch_mesh()),
        "textures/duck.png": lambda: encode_png(duck_texture()),
        "textures/tiles.png": lambda: encode_png(tiles_texture()),
        "textures/wood.png": lambda: encode_png(wood_texture()),
    }
    return {path: builders[path]() for path in ASSET_PATHS}


def write_assets(out_dir: Path) -> list[Path]:
    """Write every asset under ``out_dir`` (creating folders) and return the written paths."""
    written = []
    for relative, data in build_assets().items():
        path = out_dir / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point: ``python -m tools.make_assets [--out DIR]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--out", type=Path, default=_DEFAULT_OUT, help="output folder (default: repo scenes/)"
    )
    args = parser.parse_args(argv)
    for path in write_assets(args.out):
        print(f"{path}  {path.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
