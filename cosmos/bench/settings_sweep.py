"""Render settings by measurement: what detection loses, and what rendering saves, per (spp, film).

For seeded grid poses of each scene the renderer's exact ground truth (``annotate`` at the
scene's own film) gives every object's visible box. Each (film width, spp) view is rendered and
detected in this process; its detections, scaled to the scene's film, are matched to the ground
truth (same class, IoU ≥ 0.5, greedy by confidence). *recall* counts objects with at least
:data:`MIN_VISIBLE_FRACTION` of their silhouette and :data:`MIN_VISIBLE_PIXELS` pixels visible;
*precision* counts a detection correct when it matches any object, however small; *box error* is
the mean absolute box-edge difference of matched detections, in pixels of the scene's film.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any, Final

import numpy as np

from cosmos.bench.profile import InProcess
from services.common.contracts.detect import Detection
from services.common.contracts.render import ObjectAnnotation
from services.detector.letterbox import Letterbox, fit
from services.detector.postprocess import box_iou

__all__ = ["DEFINITION", "MIN_VISIBLE_FRACTION", "MIN_VISIBLE_PIXELS", "detection_sweep"]

MIN_VISIBLE_FRACTION: Final = 0.3
MIN_VISIBLE_PIXELS: Final = 40
IOU: Final = 0.5
FILM_SCALES: Final = (1.0, 0.75, 0.5)

DEFINITION: Final = (
    f"Seeded grid poses per scene; ground truth from the renderer's exact per-pixel object ids "
    f"at the scene's film (320×240). Recall over objects with ≥ {MIN_VISIBLE_FRACTION:.0%} of "
    f"their silhouette and ≥ {MIN_VISIBLE_PIXELS} px visible; precision over all detections "
    f"(a match: same class, IoU ≥ {IOU}); box error: mean |edge difference| of matches, in "
    "pixels of the 320×240 film. Smaller films are scaled up by the detector's letterbox."
)


def _match(
    detections: Sequence[Detection], truth: Sequence[ObjectAnnotation], view: Letterbox
) -> tuple[int, int, int, list[float]]:
    """(expected objects found, expected objects, correct detections, box errors); ``view`` maps
    the detections' film onto the ground truth's (the detector's letterbox geometry)."""
    objects = [o for o in truth if o.box is not None]
    expected = {
        i
        for i, o in enumerate(objects)
        if o.visible_fraction >= MIN_VISIBLE_FRACTION and o.visible_pixels >= MIN_VISIBLE_PIXELS
    }
    if not detections or not objects:
        return 0, len(expected), 0, []
    order = sorted(range(len(detections)), key=lambda i: -detections[i].confidence)
    boxes = view.to_input(np.array([detections[i].box for i in order], dtype=np.float64))
    gt = np.array([o.box for o in objects], dtype=np.float64)
    iou = np.stack([box_iou(box, gt) for box in boxes])
    taken: set[int] = set()
    correct = 0
    errors: list[float] = []
    for row, i in enumerate(order):
        label = detections[i].label
        candidates = [
            (iou[row, j], j)
            for j, o in enumerate(objects)
            if j not in taken and o.shape == label and iou[row, j] >= IOU
        ]
        if not candidates:
            continue
        _, j = max(candidates)
        taken.add(j)
        correct += 1
        errors.append(float(np.mean(np.abs(boxes[row] - gt[j]))))
    return len(taken & expected), len(expected), correct, errors


def detection_sweep(
    scenes: Sequence[str],
    *,
    spps: Sequence[int],
    poses: int,
    seed: int,
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Detection quality and render/detect time per (film, spp), over ``poses`` per scene."""
    local = InProcess()
    try:
        local.warm_up(scenes)
        cells: dict[tuple[int, int, int], dict[str, list[float]]] = {}
        rng = np.random.default_rng(seed)
        for scene_id in scenes:
            scene = local.catalog.get(scene_id)
            grid = scene.spec.search.grid()
            camera = scene.spec.camera
            scene_film = (camera.width, camera.height)
            films = [
                (round(camera.width * factor), round(camera.height * factor))
                for factor in FILM_SCALES
            ]
            for width, height in films:  # load each film and compile its kernels untimed
                for spp in spps:
                    local.detect_rgb(
                        local.engine.render(
                            scene, grid.pose(grid.unflat(0)), width, height, spp, 0
                        ).rgb
                    )
            for flat in rng.choice(grid.size, size=min(poses, grid.size), replace=False):
                index = grid.unflat(int(flat))
                pose = grid.pose(index)
                truth = local.engine.annotate(scene, pose, camera.width, camera.height, index)
                for width, height in films:
                    for spp in spps:
                        t0 = time.perf_counter()
                        rgb = local.engine.render(scene, pose, width, height, spp, 0).rgb
                        t1 = time.perf_counter()
                        _, detections = local.detect_rgb(rgb)
                        t2 = time.perf_counter()
                        found, expected, correct, errors = _match(
                            detections, truth.objects, fit((width, height), scene_film)
                        )
                        cell = cells.setdefault(
                            (width, height, spp),
                            {k: [] for k in ("render", "detect", "tp", "gt", "ok", "n", "err")},
                        )
                        cell["render"].append((t1 - t0) * 1000)
                        cell["detect"].append((t2 - t1) * 1000)
                        cell["tp"].append(found)
                        cell["gt"].append(expected)
                        cell["ok"].append(correct)
                        cell["n"].append(len(detections))
                        cell["err"].extend(errors)
            if say is not None:
                say(f"  detection sweep: {scene_id} done")
        rows = []
        for (width, height, spp), cell in sorted(
            cells.items(), key=lambda kv: (-kv[0][0], kv[0][2])
        ):
            rows.append(
                {
                    "width": width,
                    "height": height,
                    "spp": spp,
                    "render_p50_ms": statistics.median(cell["render"]),
                    "detect_p50_ms": statistics.median(cell["detect"]),
                    "recall": sum(cell["tp"]) / max(1.0, sum(cell["gt"])),
                    "precision": sum(cell["ok"]) / max(1.0, sum(cell["n"])),
                    "box_error_p50_px": statistics.median(cell["err"]) if cell["err"] else 0.0,
                    "views": len(cell["render"]),
                }
            )
            if say is not None:
                r = rows[-1]
                say(
                    f"  {width}x{height} spp {spp:>2}: render {r['render_p50_ms']:6.1f} ms, "
                    f"detect {r['detect_p50_ms']:5.1f} ms, recall {r['recall']:.3f}, precision "
                    f"{r['precision']:.3f}, box error {r['box_error_p50_px']:.2f} px"
                )
        return {"definition": DEFINITION, "rows": rows}
    finally:
        local.close()
