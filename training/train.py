"""Train the detector on a rendered dataset, with checkpoints so a run can resume.

Run ``python -m training.train --data data/train --val data/val --run data/runs/v1 --epochs 60``.
It saves ``last.pt`` every epoch and ``best.pt`` at the best validation mAP50, and stops on its
own after ``--max-minutes`` (run it again to continue from ``last.pt``).

``--init models/detector.onnx`` fine-tunes an exported model instead of starting from random
weights (:func:`~training.warm_start.warm_start`). Its BatchNorms are folded into the convs and
stay fixed (:func:`~training.warm_start.freeze_batchnorm`); the checkpoint records the starting
model's sha256 and provenance, and the export carries them on.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from services.detector.detect import DetectOptions, detections_from_output
from services.detector.letterbox import letterbox
from training.data import LabelledImage, augment, load_dataset
from training.dataset import CLASSES, dataset_recipe
from training.loss import detection_loss
from training.metrics import Evaluation
from training.model import Detector, anchor_points
from training.warm_start import freeze_batchnorm, warm_start

__all__ = [
    "INPUT_HEIGHT",
    "INPUT_WIDTH",
    "evaluate",
    "torch_cpu",
    "main",
    "make_batch",
    "predict",
    "predict_batch",
    "save_checkpoint",
    "train_step",
    "update_ema",
]

INPUT_WIDTH, INPUT_HEIGHT = 320, 256


def make_batch(
    samples: Sequence[LabelledImage], rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Augmented images ``[B, 3, H, W]`` in [0, 1], and padded ground truth: boxes
    ``[B, M, 4]`` (input pixels), classes ``[B, M]`` (-1 for padding) and the mask of real ones."""
    images, boxes, classes = [], [], []
    for sample in samples:
        image, b, c = augment(sample, INPUT_WIDTH, INPUT_HEIGHT, rng)
        images.append(image)
        boxes.append(b)
        classes.append(c)
    m = max(1, max(len(b) for b in boxes))
    gt_boxes = torch.zeros(len(samples), m, 4)
    gt_classes = torch.full((len(samples), m), -1, dtype=torch.long)
    for i, (b, c) in enumerate(zip(boxes, classes, strict=True)):
        gt_boxes[i, : len(b)] = torch.from_numpy(b)
        gt_classes[i, : len(c)] = torch.from_numpy(c)
    batch = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float() / 255.0
    return batch, gt_boxes, gt_classes, gt_classes >= 0


def update_ema(ema: torch.nn.Module, model: torch.nn.Module, step: int) -> None:
    """Move the exponential moving average of the weights towards ``model``'s; the decay
    ``0.9995 (1 - exp(-step / 300))`` lets early steps count fully."""
    decay = 0.9995 * (1 - math.exp(-step / 300))
    with torch.no_grad():
        for e, p in zip(ema.state_dict().values(), model.state_dict().values(), strict=True):
            if e.dtype.is_floating_point:
                e.mul_(decay).add_(p.detach(), alpha=1 - decay)
            else:
                e.copy_(p)


def train_step(
    model: Detector,
    ema: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    batch: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    anchors: tuple[torch.Tensor, torch.Tensor],
    lr: float,
    step: int,
) -> tuple[torch.Tensor, dict[str, float]]:
    """One optimiser step at learning rate ``lr`` on a :func:`make_batch` batch (gradient norm
    clipped to 10), then the EMA update for step ``step + 1``; returns the loss and its parts."""
    images, gt_boxes, gt_classes, gt_mask = batch
    points, strides = anchors
    for group in optimizer.param_groups:
        group["lr"] = lr
    raw = Detector.flatten(model(images))
    loss, parts = detection_loss(raw, points, strides, gt_boxes, gt_classes, gt_mask)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()  # type: ignore[no-untyped-call]
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    optimizer.step()
    update_ema(ema, model, step + 1)
    return loss.detach(), parts


# Serving's post-processing defaults; colours are not needed to score boxes.
_SERVING = DetectOptions(colour=False)


@torch.no_grad()
def predict_batch(
    model: Detector,
    images: Sequence[NDArray[np.uint8]],
    conf: float = _SERVING.conf,
    cross_class_iou: float | None = None,
) -> list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]]:
    """Boxes (image pixels), scores and classes for RGB images, run through the network as one
    batch and through the detector service's own letterbox and post-processing (decode,
    threshold, per-class NMS), so that what is measured here is what is served."""
    prepared = [letterbox(rgb, (INPUT_WIDTH, INPUT_HEIGHT)) for rgb in images]
    x = torch.from_numpy(np.stack([tensor for tensor, _ in prepared]))
    out = model.decode(model(x), INPUT_HEIGHT, INPUT_WIDTH).numpy()
    options = replace(_SERVING, conf=conf, cross_class_iou=cross_class_iou)
    names = [str(k) for k in range(model.num_classes)]
    results = []
    for output, (_, box) in zip(out, prepared, strict=True):
        found = detections_from_output(output, box, names, None, options)
        results.append(
            (
                np.array([d.box for d in found], dtype=np.float64).reshape(-1, 4),
                np.array([d.confidence for d in found], dtype=np.float64),
                np.array([d.class_id for d in found], dtype=np.int64),
            )
        )
    return results


def predict(
    model: Detector, rgb: NDArray[np.uint8], conf: float = _SERVING.conf
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """:func:`predict_batch` of one image."""
    return predict_batch(model, [rgb], conf)[0]


def evaluate(
    model: Detector,
    samples: Sequence[LabelledImage],
    classes: Sequence[str] = CLASSES,
    batch: int = 32,
    cross_class_iou: float | None = None,
) -> dict[str, Any]:
    """P/R/mAP50 at IoU 0.5 over objects at least 60 % visible (:class:`Evaluation`), with the
    serving post-processing (``cross_class_iou`` as a scene's own model is served with)."""
    model.eval()
    evaluation = Evaluation(tuple(classes))
    for first in range(0, len(samples), batch):
        chunk = samples[first : first + batch]
        for sample, (boxes, scores, found) in zip(
            chunk,
            predict_batch(model, [s.rgb for s in chunk], cross_class_iou=cross_class_iou),
            strict=True,
        ):
            evaluation.add(boxes, scores, found, sample.boxes, sample.classes, sample.visible)
    return evaluation.report()


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """``torch.save`` to a temporary file renamed over ``path``: a checkpoint is whole or old."""
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


@contextmanager
def torch_cpu(threads: int) -> Iterator[None]:
    """PyTorch on ``threads`` CPU threads with subnormals flushed to zero, both restored after.

    Flushing matters for speed (tiny weights and moments otherwise slow CPU math several-fold),
    but it is processor state of the whole process: left on, every later float computation in
    it loses IEEE subnormals (hypothesis refuses to run then).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(before)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, action="append", required=True)
    parser.add_argument("--val", type=Path, required=True)
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--width", type=int, default=32, help="channel width of the model")
    parser.add_argument("--max-minutes", type=float, default=1e9)
    parser.add_argument("--val-limit", type=int, default=300)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--init", type=Path, default=None, help="an exported ONNX model to fine-tune"
    )
    args = parser.parse_args(argv)
    with torch_cpu(args.threads):
        return _main(args)


def _initial_model(onnx_path: Path | None, width: int) -> tuple[Detector, dict[str, Any] | None]:
    """A fresh detector of ``width``, or the exported model ``onnx_path`` to fine-tune, with the
    record of where it came from (its sidecar's sha256 and provenance)."""
    if onnx_path is None:
        return Detector(len(CLASSES), width), None
    sidecar = json.loads(onnx_path.with_suffix(".json").read_text())
    if list(sidecar["classes"]) != list(CLASSES):
        raise SystemExit(f"{onnx_path}: classes {sidecar['classes']}, expected {list(CLASSES)}")
    init = {
        "model": onnx_path.name,
        "sha256": sidecar["sha256"],
        "provenance": sidecar.get("provenance"),
    }
    return warm_start(onnx_path, CLASSES), init


def _main(args: argparse.Namespace) -> int:
    args.run.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    train = [s for root in args.data for s in load_dataset(root)]
    val = load_dataset(args.val, args.val_limit)
    print(f"{len(train)} training images, {len(val)} validation images", flush=True)
    model, init = _initial_model(args.init, args.width)
    ema = copy.deepcopy(model).eval()
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=5e-4)
    steps_per_epoch = math.ceil(len(train) / args.batch)
    total_steps = args.epochs * steps_per_epoch
    warmup = min(500, total_steps // 10)

    def lr_at(step: int) -> float:
        if step < warmup:
            return float(args.lr * (step + 1) / warmup)
        progress = (step - warmup) / max(1, total_steps - warmup)
        return float(args.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress))))

    recipes = {str(d): dataset_recipe(d) for d in [*args.data, args.val]}
    start_epoch, step, best, history = 0, 0, -1.0, []
    last = args.run / "last.pt"
    if last.exists():
        state = torch.load(last, weights_only=False)
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        optimizer.load_state_dict(state["optimizer"])
        start_epoch, step, best = state["epoch"] + 1, state["step"], state["best"]
        history = state["history"]
        started -= 60 * history[-1]["minutes"] if history else 0  # minutes count across resumes
        print(f"resumed at epoch {start_epoch}", flush=True)
    points, strides = anchor_points(INPUT_HEIGHT, INPUT_WIDTH)

    for epoch in range(start_epoch, args.epochs):
        if (time.perf_counter() - started) / 60 > args.max_minutes:
            print("time budget used; run again to resume", flush=True)
            return 0
        model.train()
        if init is not None:
            freeze_batchnorm(model)
        rng = np.random.default_rng([7, epoch])
        order = rng.permutation(len(train))
        totals = {"loss": 0.0, "box": 0.0, "cls": 0.0}
        epoch_started = time.perf_counter()
        for first in range(0, len(order), args.batch):
            batch = make_batch([train[i] for i in order[first : first + args.batch]], rng)
            loss, parts = train_step(
                model, ema, optimizer, batch, (points, strides), lr_at(step), step
            )
            step += 1
            totals["loss"] += float(loss)
            totals["box"] += parts["box"]
            totals["cls"] += parts["cls"]
        metrics = evaluate(ema, val)
        record = {
            "epoch": epoch,
            "minutes": round((time.perf_counter() - started) / 60, 2),
            "epoch_s": round(time.perf_counter() - epoch_started, 1),
            **{k: round(v / steps_per_epoch, 4) for k, v in totals.items()},
            "precision": round(float(metrics["precision"]), 4),
            "recall": round(float(metrics["recall"]), 4),
            "map50": round(float(metrics["map50"]), 4),
        }
        history.append(record)
        print(json.dumps(record), flush=True)
        state = {
            "model": model.state_dict(),
            "ema": ema.state_dict(),
            "optimizer": optimizer.state_dict(),
            "epoch": epoch,
            "step": step,
            "best": max(best, record["map50"]),
            "history": history,
            "config": {
                "width": model.width,
                "input": [INPUT_WIDTH, INPUT_HEIGHT],
                "classes": CLASSES,
            },
            "data": [str(d) for d in args.data],
            "val": str(args.val),
            "recipes": recipes,
            "train_images": len(train),
            "init": init,
        }
        if record["map50"] > best:
            best = record["map50"]
            save_checkpoint(args.run / "best.pt", state)
        save_checkpoint(last, state)
    print(f"done: best mAP50 {best:.4f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
