"""The controller's view store: what a view weighs, how many the byte limit keeps, and what a
view not kept costs to render again against one that is.

Run: ``.venv/bin/python -m benchmarks.view_store [--views 24] [--scene demo]``

A renderer runs as a process on loopback; the views go through the controller's own
:class:`~services.controller.stages.Stages` (broker, HTTP, binary PPM) into a
:class:`~services.controller.views.ViewStore` with the default limit
(``COSMOS_CONTROLLER_VIEW_CACHE_BYTES``), for the controller's default view settings and a
cheaper one. Per setting: the mean bytes of a view as the search receives it (PPM) and as the
store keeps it (PNG), the views the limit holds as PNG, and the median milliseconds of a view
asked for the first time (rendered, encoded as PNG) and again (kept).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from cosmos.launch import spawn_service, stop_service, wait_healthy
from services.common.auth import TOKEN_VARIABLE, new_token
from services.common.contracts.optimize import searchable_grid
from services.common.contracts.search import ViewSettings
from services.common.geometry.pose import GridIndex
from services.controller.broker import Broker
from services.controller.settings import ControllerSettings
from services.controller.stages import Stages
from services.controller.transport import AiohttpTransport, WithServiceToken
from services.controller.views import ViewStore

DEFAULTS = ControllerSettings()


async def measure(renderer: str, token: str, scene: str, views: int) -> dict[str, Any]:
    """The figures of every setting, over ``views`` grid poses spread over the grid."""
    broker = Broker(
        {"renderer": [renderer]},
        transport=WithServiceToken(AiohttpTransport(2.0), token),
        health_interval_s=0,
    )
    stages = Stages(
        broker, render_spp=DEFAULTS.controller_view_spp, render_width=DEFAULTS.controller_view_width
    )
    settings = {"default": stages.view_settings, "4 spp, 160 px": ViewSettings(spp=4, width=160)}
    try:
        grid = searchable_grid((await stages.scene(scene)).spec.search).grid()
        poses = [grid.unflat(i * grid.size // views) for i in range(views)]
        await stages.render(scene, poses[0])  # the scene loaded, the kernels compiled
        figures: dict[str, Any] = {}
        for name, view in settings.items():
            figures[name] = await _one_setting(stages, scene, poses, view)
        return figures
    finally:
        await broker.close()


async def _one_setting(
    stages: Stages, scene: str, poses: list[GridIndex], view: ViewSettings
) -> dict[str, Any]:
    ppm: list[int] = []

    async def render(scene_id: str, index: GridIndex, settings: ViewSettings) -> bytes:
        image = await stages.render(scene_id, index, view_settings=settings)
        ppm.append(len(image))
        return image

    store = ViewStore(render, DEFAULTS.controller_view_cache_bytes)
    first_ms, again_ms, png = [], [], []
    for index in poses:
        t0 = time.perf_counter()
        png.append(len(await store.png(scene, index, view)))
        t1 = time.perf_counter()
        await store.png(scene, index, view)
        t2 = time.perf_counter()
        first_ms.append((t1 - t0) * 1000)
        again_ms.append((t2 - t1) * 1000)
    png_kb = statistics.fmean(png) / 1024
    return {
        "spp": view.spp,
        "width": view.width,
        "ppm_kb": round(statistics.fmean(ppm) / 1024, 1),
        "png_kb": round(png_kb, 1),
        "views_kept": int(store.max_bytes / (statistics.fmean(png) + 256)),
        "first_ms_p50": round(statistics.median(first_ms), 1),
        "again_ms_p50": round(statistics.median(again_ms), 3),
        "renders": store.renders,
        "hits": store.hits,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--scene", default="demo")
    args = parser.parse_args()
    token = new_token()
    with tempfile.TemporaryDirectory() as workdir:
        renderer = spawn_service(
            "services.renderer.app:app", Path(workdir), env={TOKEN_VARIABLE: token}
        )
        try:
            wait_healthy(renderer, 120.0)
            figures = asyncio.run(measure(renderer.url, token, args.scene, args.views))
        finally:
            stop_service(renderer)
    limit = DEFAULTS.controller_view_cache_bytes
    print(json.dumps({"scene": args.scene, "limit_bytes": limit, **figures}, indent=2))


if __name__ == "__main__":
    main()
