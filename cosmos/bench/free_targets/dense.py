"""The dense stage on a free target: one render at the box solver's pose, then
:func:`services.optimizer.free.dense.refine_dense` against the target image.

The render (RGB at the target's spp, and its depth: ``POST /render`` and ``POST /render/depth``)
is made once per target at the box solver's best pose, with the intrinsics the solver used (the
target's when it gives them, else its estimate); the refinement then runs on each image
variant of the target (:data:`~.draw.FREE_VARIANTS`: clean, JPEG, noise), with the focal length
free when the target did not give its intrinsics. Such a target is refined as a search refines
it: on a film :data:`~services.common.contracts.refine.MAX_FILM_SCALE` times its own, its grey
enlarged (``cv2.INTER_CUBIC``) and the fit's tolerances in its pixels. A pose the renderer
refuses (below the ground, inside an object) keeps the box solver's estimate, with no render
spent; with ``renders=2`` the refined pose is rendered once more and refined again from there.
Without given intrinsics, a fit whose focal length moved far from the render's
(:func:`~services.optimizer.free.refit.worth_another_render`) gets one render more.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from cosmos.bench.free_targets.draw import FREE_VARIANTS, FreeTarget, FreeVariant
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.rendering import Renderer
from services.common.contracts.refine import MAX_FILM_SCALE
from services.common.contracts.render import RenderRequest
from services.common.depth_archive import DepthImage
from services.common.errors import UnprocessableError
from services.common.geometry.camera import PinholeCamera, focal_length_px
from services.common.geometry.free_camera import (
    FreeCamera,
    free_pinhole_camera,
    quaternion_of_rotation,
)
from services.optimizer.free import FreePoseAnswer
from services.optimizer.free.dense import DenseFit, refine_dense
from services.optimizer.free.edges import on_film, outline
from services.optimizer.free.focal_bounds import FocalRange
from services.optimizer.free.refit import worth_another_render
from services.renderer.client import RendererError

__all__ = [
    "DENSE",
    "DenseRun",
    "decode_gray",
    "dense_method",
    "fit_estimate",
    "near_outline",
    "render_at",
    "run_dense",
]

DENSE: Final = "dense"


def dense_method(variant: FreeVariant) -> str:
    """The dense stage's name in the tables for one image variant."""
    return f"{DENSE} {variant}"


@dataclass(frozen=True)
class DenseRun:
    """The dense estimates per method name (:func:`dense_method`), the renders one search spends
    (on the clean variant), and the refinements' wall time (all variants, no render) in ms, in
    all and per call of :func:`refine_dense`."""

    estimates: dict[str, Estimate | None]
    renders: int
    refine_ms: float
    call_ms: tuple[float, ...] = ()


def decode_gray(data: bytes) -> NDArray[np.uint8]:
    """An encoded image (PNG, JPEG) as 8-bit grey."""
    gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise ValueError("a target image does not decode")
    return np.asarray(gray, dtype=np.uint8)


def _free_camera(camera: PinholeCamera) -> FreeCamera:
    rotation = np.asarray(camera.rotation, dtype=np.float64)
    return FreeCamera(
        position=camera.position,
        quaternion_wxyz=quaternion_of_rotation(rotation.T),
        fx_px=camera.fx,
        fy_px=camera.fy,
        cx_px=camera.cx,
        cy_px=camera.cy,
    )


def near_outline(geometry: DepthImage) -> NDArray[np.bool_] | None:
    """The pixels near the render's outline, as the optimizer's ``/refine-pose`` takes them."""
    if geometry.shading is None:
        return None
    return outline(geometry.depth, geometry.objects, geometry.shading)


def render_at(
    renderer: Renderer, target: FreeTarget, camera: FreeCamera, spp: int, *, scale: int = 1
) -> tuple[NDArray[np.uint8], DepthImage, PinholeCamera] | None:
    """The render and its geometry (depth, outline shading) at ``camera`` on the target's film
    (``scale`` times as wide and high); None when refused (422)."""
    film = target.annotations.camera
    width, height = film.width * scale, film.height * scale
    request = RenderRequest(
        scene=target.scene, camera=camera, width=width, height=height, spp=spp, seed=target.index
    )
    try:
        depth = renderer.depth(request)
        png = renderer.render_png(request)
    except (UnprocessableError, RendererError) as exc:
        if getattr(exc, "status", 422) != 422:
            raise
        return None
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the renderer's PNG does not decode")
    pinhole = free_pinhole_camera(camera, width, height, film.fov_deg)
    return np.asarray(bgr[..., ::-1], dtype=np.uint8), depth, pinhole


def fit_estimate(fit: DenseFit, width: int) -> Estimate:
    """A dense fit's camera on a film ``width`` pixels wide."""
    return Estimate.of_world_to_camera(fit.rotation, fit.translation, fit.intrinsics.fov_deg(width))


def run_dense(
    target: FreeTarget,
    answer: FreePoseAnswer,
    renderer: Renderer,
    seed: int,
    *,
    spp: int = 16,
    renders: int = 1,
    scene_fov_deg: float | None = None,
) -> DenseRun:
    """The dense stage on ``target`` from the box solver's ``answer`` (module docstring); the
    image variants' noise is seeded by ``seed`` and the target's index. A focal length fitted
    stays within the lenses the optimizer considers for the scene camera's (``scene_fov_deg``:
    :class:`~services.optimizer.free.focal_bounds.FocalRange`), as ``/refine-pose`` keeps it."""
    methods = [dense_method(v) for v in FREE_VARIANTS]
    if answer.pose is None:
        return DenseRun(dict.fromkeys(methods), 0, 0.0)
    width, height = target.annotations.camera.width, target.annotations.camera.height
    images = {
        v: decode_gray(target.image(v, np.random.default_rng([seed, target.index, 3])))
        for v in FREE_VARIANTS
    }
    estimates: dict[str, Estimate | None] = {}
    fallback = Estimate(
        answer.pose.rotation(),
        np.asarray(answer.pose.position, dtype=np.float64),
        answer.pose.intrinsics.fov_deg,
    )
    scale = 1 if target.intrinsics_given else int(MAX_FILM_SCALE)
    if scale > 1:
        images = {
            v: on_film(g, (g.shape[1] * scale, g.shape[0] * scale)) for v, g in images.items()
        }
    # the pose's pixel intrinsics times the scale, on the film that many times the target's
    camera = answer.pose.in_target_pixels(scale).free_camera()
    first = render_at(renderer, target, camera, spp, scale=scale)
    lenses = None
    if scene_fov_deg is not None:
        film = (width * scale, height * scale)
        lenses = FocalRange.of(focal_length_px(scene_fov_deg, film[0]), *film)
    spent, calls = int(first is not None), []
    for variant in FREE_VARIANTS:
        rendered, estimate, budget, step = first, fallback, renders, 0
        while rendered is not None and step < budget:
            rgb, geometry, pinhole = rendered
            started = time.perf_counter()
            fit = refine_dense(
                images[variant],
                rgb,
                geometry.depth,
                pinhole,
                fit_focal=not target.intrinsics_given,
                near=near_outline(geometry),
                pixel=float(scale),
                focal_range=lenses,
            )
            calls.append((time.perf_counter() - started) * 1000.0)
            estimate = fit_estimate(fit, width * scale)
            step += 1
            if step == budget == renders and worth_another_render(fit, pinhole):
                budget += 1
            if step < budget:
                camera = _free_camera(fit.camera(pinhole))
                rendered = render_at(renderer, target, camera, spp, scale=scale)
                spent += int(rendered is not None and variant == FREE_VARIANTS[0])
        estimates[dense_method(variant)] = estimate
    return DenseRun(estimates, spent, sum(calls), tuple(calls))
