"""Tiled detection of drone-sized views: how many objects each tiling names right.

Run: ``.venv/bin/python -m benchmarks.tiled_detection [--seeds 1,2] [--n 8] [--width 1280]
[--fov-range 0.55,1.8] [--tiles 0,2,3] [--random-scenes 2]``

Targets: the free bench's draw (``cosmos.bench.free_targets``: distance 0.4-1.6 radii,
elevation 10-90° with nadir views, roll ±25°), its lens within ``--fov-range`` times the scene
camera's fov, of the built-in scenes (their own models) and of ``--random-scenes`` generated
scenes per seed (the shipped general model), rendered ``--width`` pixels wide at 16 samples.

Each view goes through the detector's own :class:`~services.detector.detect.Detector` (decode,
letterbox, batcher, merge) with ``COSMOS_DETECTOR_TILES`` at each ``--tiles``. An object at
least 60 % visible is *named right* when a detection covers its visible box (IoU ≥ 0.5) under
its name (its shape for the general model); a detection that covers no object's box
(IoU < 0.3 with every one) is *spurious*. It prints, per model and band of the lens' factor,
the objects named right and the spurious detections, and the median detection time; then what
each tiling added to the whole image's detections (right, wrongly named, part of an object, on
nothing) with their confidence quartiles.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cosmos.bench.free_targets.draw import draw_targets
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.scenes import generate_scene
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.detect import DetectResponse
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.detector.detect import Detector
from services.detector.model import DetectorModel
from services.detector.postprocess import box_iou
from services.detector.registry import load_scene_model
from services.detector.settings import DetectorSettings


def _iou(a: Sequence[float], b: Sequence[float]) -> float:
    """The detector's IoU (:func:`services.detector.postprocess.box_iou`) of two boxes."""
    return float(box_iou(np.asarray(a, dtype=np.float64), np.asarray([b], dtype=np.float64))[0])


def scored(response: DetectResponse, truth: RenderAnnotations, own: bool) -> tuple[int, int, int]:
    """Objects at least 60 % visible, those named right, and the spurious detections."""
    usable = [o for o in truth.objects if o.box is not None and o.visible_fraction >= 0.6]
    right = sum(
        any(
            d.label == (o.name if own else o.shape) and _iou(d.box, o.box) >= 0.5
            for d in response.detections
        )
        for o in usable
        if o.box is not None
    )
    boxes = [o.box for o in truth.objects if o.box is not None]
    spurious = sum(all(_iou(d.box, b) < 0.3 for b in boxes) for d in response.detections)
    return len(usable), right, spurious


async def _detect_all(
    model: DetectorModel, tiles: int, images: Sequence[bytes]
) -> list[tuple[DetectResponse, float]]:
    detector = Detector(model, DetectorSettings(detector_tiles=tiles))
    await detector.start()
    try:
        out = []
        for data in images:
            started = time.perf_counter()
            response = await detector.detect(data)
            out.append((response, (time.perf_counter() - started) * 1000.0))
        return out
    finally:
        await detector.close()


def added_kinds(
    base: DetectResponse, tiled: DetectResponse, truth: RenderAnnotations, own: bool
) -> list[tuple[str, float]]:
    """What a tiling added to the whole image's detections (none of the same name with IoU >
    0.5 there): each as ``right`` (an object's box, IoU ≥ 0.5, under its name), ``wrong name``
    (its box under another), ``on nothing`` (IoU < 0.3 with every object's box) or ``part``,
    with its confidence."""
    boxes = [o for o in truth.objects if o.box is not None]
    out = []
    for d in tiled.detections:
        if any(e.label == d.label and _iou(e.box, d.box) > 0.5 for e in base.detections):
            continue
        best = max(boxes, key=lambda o: _iou(d.box, o.box or d.box), default=None)
        overlap = 0.0 if best is None or best.box is None else _iou(d.box, best.box)
        kind = "on nothing" if overlap < 0.3 else "part"
        if best is not None and overlap >= 0.5:
            kind = "right" if d.label == (best.name if own else best.shape) else "wrong name"
        out.append((kind, d.confidence))
    return out


def _band(factor: float) -> str:
    return "< 0.7" if factor < 0.7 else ("0.7-1.3" if factor <= 1.3 else "> 1.3")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--n", type=int, default=8)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--fov-range", default="0.55,1.8")
    parser.add_argument("--tiles", default="0,2,3")
    parser.add_argument("--random-scenes", type=int, default=2)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    low, high = (float(v) for v in args.fov_range.split(","))
    tilings = [int(t) for t in args.tiles.split(",")]
    general = DetectorModel(DetectorSettings().detector_model)
    # (model kind, band, tiles) -> [objects, named right, spurious, views]; and times per tiles
    table: dict[tuple[str, str, int], list[int]] = defaultdict(lambda: [0, 0, 0, 0])
    times: dict[int, list[float]] = defaultdict(list)
    added: dict[tuple[str, int], list[tuple[str, float]]] = defaultdict(list)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for i in range(args.random_scenes):
                generate_scene(np.random.default_rng([seed, i]), Path(tmp), f"rand{seed}-{i}")
        catalog = SceneCatalog([BUILTIN_SCENES_DIR, Path(tmp)])
        with LocalRenderer(catalog) as renderer:
            for seed in seeds:
                ids = ["demo", "garden", *(f"rand{seed}-{i}" for i in range(args.random_scenes))]
                for scene_id in ids:
                    scene = catalog.get(scene_id)
                    own = not scene_id.startswith("rand")
                    model = load_scene_model(scene) if own else general
                    spec = scene.spec.camera
                    height = round(args.width * spec.height / spec.width)
                    views = []
                    for target in draw_targets(
                        renderer, scene, scene_shapes(scene), args.n, seed, fov_range=(low, high)
                    ):
                        request = RenderRequest(
                            scene=scene_id, camera=target.camera, width=args.width,
                            height=height, spp=16, seed=target.index,
                        )  # fmt: skip
                        factor = (target.camera.fov_deg or spec.fov_deg) / spec.fov_deg
                        views.append(
                            (renderer.render_png(request), renderer.annotations(request), factor)
                        )
                    base = None
                    for tiles in tilings:
                        found = asyncio.run(_detect_all(model, tiles, [png for png, _, _ in views]))
                        if tiles == 0:
                            base = found
                        elif base is not None:
                            for (b, _), (t, _), (_, truth, _) in zip(
                                base, found, views, strict=True
                            ):
                                kind = "own" if own else "general"
                                added[(kind, tiles)] += added_kinds(b, t, truth, own)
                        for (response, ms), (_, truth, factor) in zip(found, views, strict=True):
                            row = table[("own" if own else "general", _band(factor), tiles)]
                            usable, right, spurious = scored(response, truth, own)
                            row[0] += usable
                            row[1] += right
                            row[2] += spurious
                            row[3] += 1
                            times[tiles].append(ms)
                    print(f"seed {seed} {scene_id}: {len(views)} views", flush=True)
    print(
        f"\n{args.width} px wide views, lens {low:g}-{high:g} x the scene camera's fov, "
        f"seeds {args.seeds}"
    )
    print("| model | fov factor | tiles | views | named right | spurious |")
    print("|---|---|---|---|---|---|")
    for (kind, band, tiles), (usable, right, spurious, n) in sorted(table.items()):
        print(
            f"| {kind} | {band} | {tiles} | {n} | {right}/{usable} "
            f"({right / max(usable, 1):.0%}) | {spurious} |"
        )
    for tiles in tilings:
        rows = [v for (_, _, t), v in table.items() if t == tiles]
        usable, right, spurious = (sum(r[k] for r in rows) for k in range(3))
        print(
            f"tiles {tiles}: named right {right}/{usable} ({right / max(usable, 1):.1%}), "
            f"spurious {spurious}, median detection {statistics.median(times[tiles]):.0f} ms"
        )
    for (kind, tiles), items in sorted(added.items()):
        parts = []
        for what in ("right", "wrong name", "part", "on nothing"):
            conf = sorted(c for k, c in items if k == what)
            if not conf:
                parts.append(f"{what} 0")
                continue
            quartiles = "/".join(f"{conf[int(q * (len(conf) - 1))]:.2f}" for q in (0.25, 0.5, 0.75))
            parts.append(f"{what} {len(conf)} (confidence {quartiles})")
        print(f"{kind} model, tiles {tiles} added to the whole image's: " + ", ".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
