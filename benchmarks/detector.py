"""Detector accuracy and latency on held-out renders: prints precision, recall, mAP50, p50 ms.

Run: ``.venv/bin/python -m benchmarks.detector [--count 300] [--seed 2] [--card FILE]``

The held-out images come from the dataset generator with a seed never used for training (both
built-in scenes and random ones), a third of them (``--drone-share``) from a drone: any distance,
mostly down, rolled, another fov. Ground truth is the renderer's. Printed: precision and recall at
IoU 0.5 for objects with at least 60 % of their silhouette visible, per class, per scene, per kind
of view (hemisphere or drone) and overall; mAP50; box-centre error; colour error (the detection's
colour against the mean of the object's own pixels); latency p50 per 320x240 image through the HTTP
API of a real detector process and in-process, side by side. ``--card`` rewrites the model card
with these figures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from cosmos.launch import running_service
from services.common.contracts.detect import DetectResponse
from services.common.geometry.free_camera import FreeCamera
from services.detector.client import DetectorClient
from services.detector.detect import Detector
from services.detector.model import DetectorModel
from services.detector.settings import DetectorSettings
from services.renderer.engine import RenderEngine
from services.renderer.imaging import encode_png
from training.card import write_general_card
from training.dataset import CLASSES, asset_folder, views
from training.drone_views import engine_view
from training.metrics import Evaluation, box_iou

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "detector.onnx"
DRONE_SHARE = 1 / 3


def _arrays(response: DetectResponse) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    boxes = np.array([d.box for d in response.detections], dtype=np.float64).reshape(-1, 4)
    scores = np.array([d.confidence for d in response.detections])
    classes = np.array([CLASSES.index(d.label) for d in response.detections], dtype=np.int64)
    return boxes, scores, classes


def _colour_errors(
    response: DetectResponse, rgb: np.ndarray, object_map: np.ndarray, gt: list[Any]
) -> list[float]:
    """Euclidean RGB (0–255) error of each detection matched to a counted object."""
    errors = []
    gt_boxes = np.array([o.box for o in gt], dtype=np.float64).reshape(-1, 4)
    for det in response.detections:
        if det.color is None or not len(gt_boxes):
            continue
        ious = box_iou(np.array([det.box]), gt_boxes)[0]
        j = int(np.argmax(ious))
        if ious[j] < 0.5 or gt[j].shape != det.label or gt[j].visible_fraction < 0.6:
            continue
        pixels = rgb[object_map == gt[j].index]
        if len(pixels) < 20:
            continue
        errors.append(float(np.linalg.norm(np.array(det.color) - pixels.mean(axis=0))))
    return errors


async def _in_process(detector: Detector, png: bytes) -> tuple[DetectResponse, float]:
    started = time.perf_counter()
    response = await detector.detect(png)
    return response, (time.perf_counter() - started) * 1000


def run(count: int, seed: int, model: Path, drone_share: float = DRONE_SHARE) -> dict[str, Any]:
    engine = RenderEngine("auto", cache_size=2)
    engine.start()
    settings = DetectorSettings(detector_model=model)
    evaluation = Evaluation(CLASSES)
    by_scene: dict[str, Evaluation] = {}
    by_view: dict[str, Evaluation] = {}
    http_ms: list[float] = []
    local_ms: list[float] = []
    colour_errors: list[float] = []
    scenes: set[str] = set()
    loop = asyncio.new_event_loop()
    detector = Detector(DetectorModel(model, threads=settings.detector_threads), settings)
    loop.run_until_complete(detector.start())
    with (
        tempfile.TemporaryDirectory() as tmp,
        running_service(
            "services.detector.app:app", Path(tmp) / "logs", {"COSMOS_DETECTOR_MODEL": str(model)}
        ) as service,
        DetectorClient(service.url, token=service.token) as client,
    ):
        todo = views(
            asset_folder(Path(tmp)), seed, count, builtin_share=0.35, drone_share=drone_share
        )
        for view in todo:
            group = view.scene.id if not view.scene.id.startswith("s") else "random"
            scenes.add(group)
            drone = isinstance(view.pose, FreeCamera)
            where = engine_view(view.scene, view.pose, view.width, view.height)
            rgb = engine.render(view.scene, where, view.width, view.height, view.spp, view.seed).rgb
            ann = engine.annotate(view.scene, where, view.width, view.height, None)
            object_map = engine.object_map(view.scene, where, view.width, view.height)
            png = encode_png(rgb)
            started = time.perf_counter()
            response = client.detect(png)
            elapsed = (time.perf_counter() - started) * 1000
            local, local_elapsed = loop.run_until_complete(_in_process(detector, png))
            if (view.width, view.height) == (320, 240):
                http_ms.append(elapsed)
                local_ms.append(local_elapsed)
            gt = [
                _Gt(i, o.shape, o.box, o.visible_fraction)
                for i, o in enumerate(ann.objects)
                if o.box is not None and o.visible_pixels >= 6
            ]
            boxes, scores, classes = _arrays(response)
            truth = (
                np.array([g.box for g in gt]).reshape(-1, 4),
                np.array([CLASSES.index(g.shape) for g in gt], dtype=np.int64),
                np.array([g.visible_fraction for g in gt]),
            )
            evaluation.add(boxes, scores, classes, *truth)
            by_scene.setdefault(group, Evaluation(CLASSES)).add(boxes, scores, classes, *truth)
            kind = "drone" if drone else "hemisphere"
            by_view.setdefault(kind, Evaluation(CLASSES)).add(boxes, scores, classes, *truth)
            colour_errors.extend(_colour_errors(response, rgb, object_map, gt))
    loop.run_until_complete(detector.close())
    loop.close()
    engine.close()
    report = evaluation.report()
    report.update(
        {
            "images": count,
            "seed": seed,
            "scenes": sorted(scenes),
            "latency_http_p50_ms": float(np.median(http_ms)) if http_ms else None,
            "latency_in_process_p50_ms": float(np.median(local_ms)) if local_ms else None,
            "latency_images": len(http_ms),
            "colour_error_median": float(np.median(colour_errors)) if colour_errors else None,
            "colour_error_p95": float(np.percentile(colour_errors, 95)) if colour_errors else None,
            "model_sha256": DetectorModel(model).info.sha256,
            "by_scene": {name: ev.report() for name, ev in sorted(by_scene.items())},
            "drone_share": drone_share,
            "by_view": {name: ev.report() for name, ev in sorted(by_view.items())},
        }
    )
    return report


class _Gt:
    def __init__(self, index: int, shape: str, box: Any, visible_fraction: float) -> None:
        self.index, self.shape, self.box, self.visible_fraction = (
            index,
            shape,
            box,
            visible_fraction,
        )


def table(report: dict[str, Any]) -> str:
    lines = [
        f"held-out images: {report['images']} (seed {report['seed']}; scenes: "
        f"{', '.join(report['scenes'])}), objects >= 60 % visible: {report['objects']}",
        f"{'class':<12} {'objects':>8} {'precision':>10} {'recall':>8} {'AP50':>7}",
    ]
    for name, row in report["per_class"].items():
        lines.append(
            f"{name:<12} {int(row['objects']):>8} {row['precision']:>10.3f} {row['recall']:>8.3f} "
            f"{row['ap50']:>7.3f}"
        )
    lines.append(
        f"{'overall':<12} {report['objects']:>8} {report['precision']:>10.3f} "
        f"{report['recall']:>8.3f} {report['map50']:>7.3f} (mAP50)"
    )
    for name, part in report.get("by_scene", {}).items():
        lines.append(
            f"{'  ' + name:<12} {part['objects']:>8} {part['precision']:>10.3f} "
            f"{part['recall']:>8.3f} {part['map50']:>7.3f} (scene {name})"
        )
    for name, part in report.get("by_view", {}).items():
        lines.append(
            f"{'  ' + name:<12} {part['objects']:>8} {part['precision']:>10.3f} "
            f"{part['recall']:>8.3f} {part['map50']:>7.3f} ({name} views)"
        )
    lines.append(
        f"box-centre error: median {report['centre_error_median_px']:.2f} px, "
        f"p95 {report['centre_error_p95_px']:.2f} px"
    )
    if report["colour_error_median"] is not None:
        lines.append(
            f"colour error (RGB 0-255, Euclidean): median {report['colour_error_median']:.1f}, "
            f"p95 {report['colour_error_p95']:.1f}"
        )
    lines.append(
        f"latency p50 per 320x240 image ({report['latency_images']} images): HTTP "
        f"{report['latency_http_p50_ms']:.1f} ms, "
        f"in-process {report['latency_in_process_p50_ms']:.1f} ms"
    )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=300)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--model", type=Path, default=MODEL)
    parser.add_argument(
        "--drone-share", type=float, default=DRONE_SHARE, help="share of drone views"
    )
    parser.add_argument("--json", type=Path, help="also write the figures as JSON here")
    parser.add_argument("--card", type=Path, help="rewrite this model card with the figures")
    args = parser.parse_args()
    report = run(args.count, args.seed, args.model, args.drone_share)
    text = table(report)
    print(text)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    if args.card:
        write_general_card(args.card, args.model, report, text)
        print(f"wrote {args.card}")


if __name__ == "__main__":
    main()
