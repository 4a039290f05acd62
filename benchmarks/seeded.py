"""The scenes the in-process benchmarks measure on: per seed, the demo and scenes generated from
that seed (:func:`cosmos.bench.scenes.generate_scenes`), each with a renderer that serves it."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.scenes import generate_scenes
from services.common.catalog import SceneCatalog
from services.renderer.settings import RendererSettings

__all__ = ["seeded_scenes"]


def seeded_scenes(
    seeds: Iterable[int], random_scenes: int
) -> Iterator[tuple[LocalRenderer, SceneCatalog, str, int]]:
    """Per seed, the demo and ``random_scenes`` scenes generated from it (in a temporary folder,
    gone when the iteration ends): the renderer, the catalog holding them, the scene's id and
    the seed."""
    settings = RendererSettings()
    with tempfile.TemporaryDirectory() as work:
        for seed in seeds:
            ids = ["demo", *generate_scenes(random_scenes, seed, Path(work))]
            catalog = SceneCatalog([*settings.scene_directories(), Path(work)])
            with LocalRenderer(catalog, settings) as renderer:
                for scene_id in ids:
                    yield renderer, catalog, scene_id, seed
