"""Target images of the evaluation: where they are taken from and how they are degraded.

Six variants, reported separately:

``clean``
    A grid pose, rendered as the renderer delivers it (PNG).
``jpeg``
    The same, re-encoded as JPEG at quality 60 (what a phone or a web upload does to it).
``noise``
    The same with additive Gaussian pixel noise, σ = 6 on the 0–255 scale, per channel.
``offgrid``
    A continuous pose: a grid pose moved by up to a third of a step in θ (``Δ/3``) and in φ
    (a third of that ring's spacing ``360°/n_k``), rendered at the continuous pose. Its ground
    truth is the grid pose nearest to it by great-circle angle (:meth:`HemisphereGrid.nearest`),
    which need not be the grid pose it was drawn around.
``photo``
    "A photo, not a render": a grid pose rendered from a copy of the scene whose point light is
    moved and scaled (:mod:`cosmos.bench.altered`), then finished as a camera would
    (:func:`photo_finish`): exposure ×[0.7, 1.4] in linear light, a display gamma
    ``v' = v^γ``, γ ∈ [0.8, 1.25], and a Gaussian blur of σ ∈ [0.4, 0.9] px.
``changed``
    "The scene changed": a grid pose rendered from a copy of the scene with one object moved by
    0.5–1.5 units on the ground or left out (:mod:`cosmos.bench.altered`). The search runs in
    the original scene.

Every draw comes from a :class:`numpy.random.Generator` the caller seeds, so a bench run is
reproducible to the pixel (the renderer is deterministic for a given seed).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Final, Literal, get_args

import cv2
import numpy as np
from numpy.typing import NDArray
from PIL import ExifTags, Image

from services.common.geometry.free_camera import LensDistortion
from services.common.geometry.grid import HemisphereGrid
from services.common.geometry.pose import GridIndex, Pose

__all__ = [
    "JPEG_QUALITY",
    "NOISE_SIGMA",
    "OFFGRID_FRACTION",
    "SCENE_VARIANTS",
    "VARIANTS",
    "TargetPose",
    "Variant",
    "degrade",
    "draw_pose",
    "exif_jpeg",
    "photo_finish",
]

Variant = Literal["clean", "jpeg", "noise", "offgrid", "photo", "changed"]
VARIANTS: Final[tuple[Variant, ...]] = get_args(Variant)
SCENE_VARIANTS: Final[tuple[Variant, ...]] = ("photo", "changed")
"""Variants whose targets are rendered from a modified copy of the scene."""

JPEG_QUALITY: Final = 60
NOISE_SIGMA: Final = 6.0
"""Standard deviation of the pixel noise, on the 0–255 scale."""
OFFGRID_FRACTION: Final = 1.0 / 3.0
"""Off-grid targets lie up to this fraction of a step from a grid pose, in θ and in φ."""
EXPOSURE: Final = (0.7, 1.4)
GAMMA: Final = (0.8, 1.25)
BLUR_SIGMA_PX: Final = (0.4, 0.9)


@dataclass(frozen=True)
class TargetPose:
    """Where a target is taken from: the pose rendered and the grid pose a search must find."""

    pose: Pose
    truth: GridIndex
    on_grid: bool


def draw_pose(grid: HemisphereGrid, variant: Variant, rng: np.random.Generator) -> TargetPose:
    """A uniformly drawn grid pose, moved off the grid for ``offgrid`` (module docstring).

    θ stays within [0°, 90°] (a move past the horizon or the zenith is reflected back).
    """
    flat = int(rng.integers(grid.size))
    index = grid.unflat(flat)
    base = grid.pose(index)
    if variant != "offgrid":
        return TargetPose(pose=base, truth=index, on_grid=True)
    step = grid.angle_step_deg
    d_theta, d_phi = rng.uniform(-OFFGRID_FRACTION, OFFGRID_FRACTION, size=2)
    theta = base.theta_deg + d_theta * step
    theta = abs(theta) if theta < 0.0 else (180.0 - theta if theta > 90.0 else theta)
    phi = base.phi_deg + d_phi * 360.0 / grid.ring_size(index.lat)
    pose = Pose(theta_deg=theta, phi_deg=phi)
    return TargetPose(pose=pose, truth=grid.nearest(pose), on_grid=False)


def degrade(png: bytes, variant: Variant, rng: np.random.Generator) -> bytes:
    """The target image of ``variant`` from the renderer's PNG (``clean``, ``offgrid`` and
    ``changed``: as is).

    ``jpeg`` re-encodes at :data:`JPEG_QUALITY`; ``noise`` adds N(0, :data:`NOISE_SIGMA`²) per
    pixel and channel, rounds and clips to 0–255, and encodes PNG again; ``photo`` is
    :func:`photo_finish`.
    """
    if variant in ("clean", "offgrid", "changed"):
        return png
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the renderer's PNG does not decode")
    if variant == "photo":
        finished = photo_finish(np.asarray(bgr, dtype=np.uint8), rng)
        ok, buffer = cv2.imencode(".png", finished, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    elif variant == "jpeg":
        ok, buffer = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    else:
        noisy = bgr.astype(np.float64) + rng.normal(0.0, NOISE_SIGMA, size=bgr.shape)
        out = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        ok, buffer = cv2.imencode(".png", out, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"encoding the {variant} target failed")
    return bytes(buffer)


def photo_finish(bgr: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[np.uint8]:
    """A rendered 8-bit sRGB image as a camera might have delivered it.

    With ``v`` in [0, 1]: linearise (``v^2.2``), scale by an exposure ``e`` ~ U(0.7, 1.4), back to
    display (``^(1/2.2)``), apply a gamma ``γ`` ~ U(0.8, 1.25) (``v' = v^γ``), clip, blur with a
    Gaussian of σ ~ U(0.4, 0.9) px and round. (2.2 stands for the sRGB curve: a photo's is not
    known either.)
    """
    exposure, gamma = rng.uniform(*EXPOSURE), rng.uniform(*GAMMA)
    sigma = float(rng.uniform(*BLUR_SIGMA_PX))
    v = bgr.astype(np.float64) / 255.0
    v = np.clip((v**2.2 * exposure) ** (1 / 2.2), 0.0, 1.0) ** gamma
    blurred = cv2.GaussianBlur(v * 255.0, (0, 0), sigmaX=sigma)
    out: NDArray[np.uint8] = np.clip(np.rint(blurred), 0, 255).astype(np.uint8)
    return out


def dji_xmp(
    focal: tuple[float, float],
    centre: tuple[float, float],
    size: tuple[int, int],
    lens: LensDistortion | None,
    *,
    dewarped: bool = False,
    attitude: tuple[float, float] | None = None,
) -> bytes:
    """The XMP packet a DJI survey drone writes for a photo of ``size`` pixels taken through a
    calibrated lens: focal lengths ``focal`` (px), principal point ``centre`` (px, written as its
    offset from the photo's centre), ``lens`` (k1, k2, p1, p2, k3), ``DewarpFlag``, and the
    gimbal's angles for a camera ``attitude`` (pitch, roll in this project's conventions: DJI's
    pitch is its negative) when given (:mod:`services.controller.photo_xmp` reads them)."""
    d = lens or LensDistortion()
    offset = (centre[0] - size[0] / 2, centre[1] - size[1] / 2)
    numbers = [*focal, *offset, d.k1, d.k2, d.p1, d.p2, d.k3]
    dewarp = "2024-05-01;" + ",".join(f"{v:.12f}" for v in numbers)
    gimbal = (
        ""
        if attitude is None
        else f'drone-dji:GimbalPitchDegree="{-attitude[0]:+.2f}" '
        f'drone-dji:GimbalRollDegree="{attitude[1]:+.2f}" drone-dji:GimbalYawDegree="-79.00" '
    )
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
        'rdf:about="DJI Meta Data" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
        f'{gimbal}drone-dji:DewarpData="{dewarp}" '
        f'drone-dji:DewarpFlag="{int(dewarped)}"/></rdf:RDF></x:xmpmeta>'
    ).encode()


def exif_jpeg(png: bytes, focal_35mm: int, xmp: bytes | None = None) -> bytes:
    """``png`` as a camera's JPEG (quality 92) whose EXIF states ``focal_35mm`` as
    FocalLengthIn35mmFilm (a free search reads it: :mod:`services.controller.photo_exif`), with
    the ``xmp`` packet if any (:func:`dji_xmp`)."""
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = focal_35mm
    out = io.BytesIO()
    extra = {} if xmp is None else {"xmp": xmp}
    Image.open(io.BytesIO(png)).convert("RGB").save(out, "JPEG", quality=92, exif=exif, **extra)
    return out.getvalue()
