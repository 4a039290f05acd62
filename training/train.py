"""Train the detector on a rendered dataset, with checkpoints so a run can resume.

Run ``python -m training.train --data data/train --val data/val --run data/runs/v1 --epochs 60``.
It saves ``last.pt`` every epoch and ``best.pt`` at the best validation mAP50, and stops on its
own after ``--max-minutes`` (run it again to continue from ``last.pt``).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from training.data import LabelledImage, augment, letterbox, load_dataset
from training.dataset import CLASSES
from training.loss import detection_loss
from training.metrics import Evaluation, nms
from training.model import Detector, anchor_points

__all__ = ["INPUT_HEIGHT", "INPUT_WIDTH", "main", "predict", "predict_batch"]

INPUT_WIDTH, INPUT_HEIGHT = 320, 256


def _batch(
    samples: Sequence[LabelledImage], rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
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


def _postprocess(
    out: np.ndarray,
    scale: float,
    pad_x: float,
    pad_y: float,
    size: tuple[int, int],
    conf: float,
    iou: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's decoded predictions ``[N, 4 + C]`` to boxes in its pixels, scores, classes."""
    scores = out[:, 4:].max(1)
    classes = out[:, 4:].argmax(1)
    keep = scores >= conf
    cxcy, wh, scores, classes = out[keep, :2], out[keep, 2:4], scores[keep], classes[keep]
    boxes = np.concatenate([cxcy - wh / 2, cxcy + wh / 2], axis=1)
    boxes = (boxes - [pad_x, pad_y, pad_x, pad_y]) / scale
    w, h = size
    boxes = np.clip(boxes, 0, [w, h, w, h])
    kept = nms(boxes, scores, classes, iou)
    return boxes[kept], scores[kept], classes[kept]


@torch.no_grad()
def predict_batch(
    model: Detector, images: Sequence[np.ndarray], conf: float = 0.25, iou: float = 0.6
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Boxes (image pixels), scores and classes for RGB images (centred letterbox, NMS), run
    through the network as one batch."""
    boxes = [letterbox(rgb, INPUT_WIDTH, INPUT_HEIGHT) for rgb in images]
    x = torch.from_numpy(np.stack([b[0] for b in boxes])).permute(0, 3, 1, 2).float() / 255.0
    out = model.decode(model(x), INPUT_HEIGHT, INPUT_WIDTH).transpose(1, 2).numpy()
    return [
        _postprocess(o, scale, pad_x, pad_y, (rgb.shape[1], rgb.shape[0]), conf, iou)
        for o, (_, scale, pad_x, pad_y), rgb in zip(out, boxes, images, strict=True)
    ]


def predict(
    model: Detector, rgb: np.ndarray, conf: float = 0.25, iou: float = 0.6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`predict_batch` of one image."""
    return predict_batch(model, [rgb], conf, iou)[0]


def evaluate(model: Detector, samples: Sequence[LabelledImage], batch: int = 32) -> dict[str, Any]:
    """P/R/mAP50 at IoU 0.5 over objects at least 60 % visible."""
    model.eval()
    evaluation = Evaluation(CLASSES)
    for first in range(0, len(samples), batch):
        chunk = samples[first : first + batch]
        for sample, (boxes, scores, classes) in zip(
            chunk, predict_batch(model, [s.rgb for s in chunk]), strict=True
        ):
            evaluation.add(boxes, scores, classes, sample.boxes, sample.classes, sample.visible)
    return evaluation.report()


def _save(path: Path, state: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


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
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)  # tiny weights and moments otherwise slow CPU math several-fold
    args.run.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    train = [s for root in args.data for s in load_dataset(root)]
    val = load_dataset(args.val, args.val_limit)
    print(f"{len(train)} training images, {len(val)} validation images", flush=True)
    model = Detector(len(CLASSES), args.width)
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
        rng = np.random.default_rng([7, epoch])
        order = rng.permutation(len(train))
        totals = {"loss": 0.0, "box": 0.0, "cls": 0.0}
        epoch_started = time.perf_counter()
        for first in range(0, len(order), args.batch):
            images, gt_boxes, gt_classes, gt_mask = _batch(
                [train[i] for i in order[first : first + args.batch]], rng
            )
            for group in optimizer.param_groups:
                group["lr"] = lr_at(step)
            raw = Detector.flatten(model(images))
            loss, parts = detection_loss(raw, points, strides, gt_boxes, gt_classes, gt_mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            optimizer.step()
            step += 1
            decay = 0.9995 * (1 - math.exp(-step / 300))
            with torch.no_grad():
                for e, p in zip(
                    ema.state_dict().values(), model.state_dict().values(), strict=True
                ):
                    if e.dtype.is_floating_point:
                        e.mul_(decay).add_(p.detach(), alpha=1 - decay)
                    else:
                        e.copy_(p)
            totals["loss"] += float(loss.detach())
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
                "width": args.width,
                "input": [INPUT_WIDTH, INPUT_HEIGHT],
                "classes": CLASSES,
            },
            "data": [str(d) for d in args.data],
            "train_images": len(train),
        }
        if record["map50"] > best:
            best = record["map50"]
            _save(args.run / "best.pt", state)
        _save(last, state)
    print(f"done: best mAP50 {best:.4f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
