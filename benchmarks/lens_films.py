"""Renders through many lenses: a distorted view's rendered film padded to a step, or not.

Run: ``.venv/bin/python -m benchmarks.lens_films [--scene demo] [--lenses 10] [--repeat 2]``

A distorted (or ``fx ≠ fy``) free camera is rendered through a pinhole on a film just large
enough for its rays (:mod:`services.renderer.free_view`), a film size of its own per lens. The
engine loads the scene, and records its frozen render, once per film size, and a free search
that estimates a photo's lens renders through a new one each time. This renders the oblique
view of ``--scene`` at 320 x 240, 8 samples a pixel, through ``--lenses`` radial lenses (``k1``
evenly from −0.05 to −0.15), ``--repeat`` times over, in a fresh engine per arm: the films as
planned (``unpadded``) and padded to :data:`~services.renderer.free_view.FILM_STEP_PX`
(``padded``). It prints per arm the distinct film sizes, the median and p90 ms a render, and
the ratio of the medians, measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.geometry.free_camera import FreeCamera, LensDistortion
from services.renderer import free_view
from services.renderer.engine import RenderEngine
from services.renderer.view import resolve_free_camera

WIDTH, HEIGHT, SPP = 320, 240, 8
VIEW = FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0), fov_deg=65.0)


def render_times(
    scene_id: str, lenses: Sequence[float], repeat: int, step: int
) -> dict[str, list[Any]]:
    """Milliseconds a render through each of ``lenses`` (``k1``), ``repeat`` times over, with
    rendered films padded to ``step`` pixels (1: as planned), in a fresh engine; and the film
    sizes rendered."""
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get(scene_id)
    kept = free_view.FILM_STEP_PX
    free_view.FILM_STEP_PX = step
    free_view._WARPS.clear()
    engine = RenderEngine("auto")
    engine.start()
    try:
        engine.render(scene, resolve_free_camera(scene, VIEW, WIDTH, HEIGHT), WIDTH, HEIGHT, SPP)
        times: list[float] = []
        films: set[tuple[int, int]] = set()
        for _ in range(repeat):
            for k1 in lenses:
                camera = VIEW.model_copy(update={"distortion": LensDistortion(k1=k1)})
                view = resolve_free_camera(scene, camera, WIDTH, HEIGHT)
                films.add((view.rendered.width, view.rendered.height))
                started = time.perf_counter()
                engine.render(scene, view, WIDTH, HEIGHT, SPP)
                times.append((time.perf_counter() - started) * 1000.0)
        return {"times": times, "films": sorted(films)}
    finally:
        engine.close()
        free_view.FILM_STEP_PX = kept
        free_view._WARPS.clear()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--lenses", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args(argv)
    lenses = [float(k) for k in np.linspace(-0.05, -0.15, args.lenses)]
    arms = {
        "unpadded": render_times(args.scene, lenses, args.repeat, 1),
        "padded": render_times(args.scene, lenses, args.repeat, free_view.FILM_STEP_PX),
    }
    print(f"{args.scene}, {WIDTH} x {HEIGHT}, {SPP} spp, {len(lenses)} lenses x {args.repeat}")
    print(f"{'arm':10s} {'films':>5s} {'median ms':>10s} {'p90 ms':>8s}")
    for name, arm in arms.items():
        times = arm["times"]
        p90 = float(np.percentile(times, 90))
        print(f"{name:10s} {len(arm['films']):5d} {statistics.median(times):10.0f} {p90:8.0f}")
    ratio = statistics.median(arms["padded"]["times"]) / statistics.median(
        arms["unpadded"]["times"]
    )
    print(f"padded / unpadded median: {ratio:.2f}")


if __name__ == "__main__":
    main()
