"""The free targets of one scene for ``cosmos bench --free``, and their images per variant.

The cameras are :func:`cosmos.bench.free_targets.draw.draw_targets`' (issue 23, item 5),
rendered by the stack's renderer. Each variant's image is the camera's view made as the
hemisphere bench makes its own (:mod:`cosmos.bench.variants`): ``clean``, ``jpeg`` and ``noise``
degrade the drawn render; ``photo`` and ``changed`` render the same camera in a modified copy of
the scene (:func:`cosmos.bench.altered.alter_scene`, a light moved, an object moved or left out)
and ``photo`` finishes it as a camera would. A copy that puts an object where the camera stands
(the renderer refuses the view) is drawn again, up to :data:`ALTER_TRIES` times.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from cosmos.bench.altered import alter_scene
from cosmos.bench.free_targets.draw import FreeTarget
from cosmos.bench.free_targets.rendering import Renderer
from cosmos.bench.variants import SCENE_VARIANTS, VARIANTS, Variant, degrade
from services.common.contracts.render import RenderRequest
from services.common.errors import UnprocessableError
from services.common.geometry.scene import LoadedScene
from services.renderer.client import RendererError

__all__ = ["ALTER_TRIES", "FREE_BENCH_VARIANTS", "VariantImage", "variant_image"]

FREE_BENCH_VARIANTS: Final[tuple[Variant, ...]] = ("clean", "jpeg", "noise", "photo", "changed")
"""The variants a free target is searched in (``offgrid`` means nothing off the grid)."""
ALTER_TRIES: Final = 5


@dataclass(frozen=True)
class VariantImage:
    """A target's image of one variant, and what its scene copy changed (``photo``,
    ``changed``)."""

    variant: Variant
    image: bytes = field(repr=False)
    change: str = ""


def _rng(seed: int, target: FreeTarget, variant: Variant) -> np.random.Generator:
    """One stream per (seed, target, variant): a target's other variants change nothing here."""
    return np.random.default_rng([seed, target.index, VARIANTS.index(variant), 5])


def variant_image(
    renderer: Renderer,
    scene: LoadedScene,
    target: FreeTarget,
    variant: Variant,
    seed: int,
    *,
    altered_dir: Path | None,
    spp: int,
) -> VariantImage | None:
    """``target``'s image of ``variant`` (module docstring); None when no copy of the scene
    could be rendered from its camera."""
    rng = _rng(seed, target, variant)
    if variant not in SCENE_VARIANTS:
        return VariantImage(variant, degrade(target.png, variant, rng))
    if altered_dir is None:
        raise ValueError("photo and changed targets need a local stack (without --url)")
    film = target.annotations.camera
    for attempt in range(ALTER_TRIES):
        copy = alter_scene(
            scene, variant, rng, altered_dir, f"{scene.id}_free_{variant}{target.index}_{attempt}"
        )
        request = RenderRequest(
            scene=copy.id,
            camera=target.camera,
            width=film.width,
            height=film.height,
            spp=spp,
            seed=target.index,
        )
        try:
            png = renderer.render_png(request)
        except (UnprocessableError, RendererError) as exc:
            if getattr(exc, "status", 422) != 422:
                raise
            continue
        return VariantImage(variant, degrade(png, variant, rng), copy.change)
    return None
