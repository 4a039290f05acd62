"""A view's per-pixel geometry as it travels between the services: the renderer's
``POST /render/depth`` (and ``POST /render`` asked for :data:`DEPTH_MEDIA_TYPE`) answers it, the
optimizer's ``POST /refine-pose`` takes it.

A NumPy ``.npz`` archive (uncompressed: ~7 bytes a pixel, 10 with the colours) of ``depth``
``(H, W)`` float32 (``Z_c`` along the optical axis, scene units, 0 where no surface),
``objects`` ``(H, W)`` int16 (the scene object's index, -1 for the ground or nothing),
``shading`` ``(H, W)`` uint8 (the view's outline shading: albedo lit from the camera, no shadows,
:mod:`services.renderer.depth`; optional) and, when the view's colours come with it, ``rgb``
``(H, W, 3)`` uint8 (sRGB): one render of a view then serves what is detected in it and what its
edges are back-projected through.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

__all__ = ["DEPTH_MEDIA_TYPE", "DepthImage"]

DEPTH_MEDIA_TYPE: Final = "application/x-npz"
"""The media type of a :meth:`DepthImage.npz` archive."""


@dataclass(frozen=True)
class DepthImage:
    """A view's ``depth`` ``(H, W)`` float32 (``Z_c`` in scene units, 0 where no surface),
    ``objects`` ``(H, W)`` int16 (the scene object's index, -1 for the ground or nothing) and,
    optionally, its colours ``rgb`` ``(H, W, 3)`` uint8 and its outline ``shading`` ``(H, W)``
    uint8 (lit from the camera: edges that do not move with the light)."""

    depth: NDArray[np.float32]
    objects: NDArray[np.int16]
    rgb: NDArray[np.uint8] | None = None
    shading: NDArray[np.uint8] | None = None

    def npz(self) -> bytes:
        """The arrays as an uncompressed ``.npz`` (``depth``, ``objects``, and ``rgb`` and
        ``shading`` when present), read back with :meth:`from_npz`."""
        buffer = io.BytesIO()
        arrays = {"depth": self.depth, "objects": self.objects}
        if self.rgb is not None:
            arrays["rgb"] = self.rgb
        if self.shading is not None:
            arrays["shading"] = self.shading
        np.savez(buffer, **arrays)  # type: ignore[arg-type]
        return buffer.getvalue()

    @classmethod
    def from_npz(cls, data: bytes) -> DepthImage:
        """The arrays of :meth:`npz` bytes (raises ``ValueError`` on anything else: no pickles,
        arrays of other shapes)."""
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as archive:
                depth = np.asarray(archive["depth"], dtype=np.float32)
                objects = np.asarray(archive["objects"], dtype=np.int16)
                rgb = np.asarray(archive["rgb"]) if "rgb" in archive.files else None
                shading = np.asarray(archive["shading"]) if "shading" in archive.files else None
        except (OSError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"not a depth archive: {exc}") from exc
        if depth.ndim != 2 or depth.shape != objects.shape:
            raise ValueError("a depth archive holds two (H, W) arrays of one shape")
        if rgb is not None and (rgb.dtype != np.uint8 or rgb.shape != (*depth.shape, 3)):
            raise ValueError("a depth archive's rgb is an (H, W, 3) uint8 array of its shape")
        if shading is not None and (shading.dtype != np.uint8 or shading.shape != depth.shape):
            raise ValueError("a depth archive's shading is an (H, W) uint8 array of its shape")
        return cls(depth=depth, objects=objects, rgb=rgb, shading=shading)
