"""Onboard a scene: train, measure and install its own detector (``cosmos scenes add``).

:func:`onboard_scene` runs four stages, each resumable:

1. *validate* the scene file (:func:`~services.common.geometry.scene.load_scene`: named-field
errors,
   meshes and textures inside the scene's folder) before anything is rendered;
2. *render* an auto-labelled dataset of the scene (:mod:`training.scene_dataset`) for training
   (seed ``s``) and a held-out one (seed ``s + 1000``, never trained on) into the work folder;
3. *train*: fine-tune the shipped general model (:mod:`training.warm_start`) with one class per
   :func:`~services.common.scene_models.object_classes` entry, BatchNorm frozen, AdamW with a
   short warm-up and a cosine decay, an exponential moving average of the weights (the model
   kept); a checkpoint ``last.pt`` every epoch, from which an interrupted run resumes;
4. *evaluate* the averaged model on the held-out renders (precision, recall, mAP50 at IoU 0.5
   over objects at least 60 % visible, through the detector service's own letterbox and
   post-processing) and *install* it into :func:`~services.common.scene_models.model_dir`:
   sidecar and model card first, then the ONNX file renamed into place, so that an interrupted
   run never leaves a half-written model (a detector trusts a model only when the sidecar's
   sha256 is the file's).

torch is imported only when training starts: the rest of the project runs without it.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import shlex
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.common.geometry.scene import LoadedScene, load_scene
from services.common.scene_models import (
    MODEL_CARD_NAME,
    MODEL_FILE_NAME,
    SIDECAR_NAME,
    model_dir,
    object_classes,
)
from services.detector.detect import SCENE_CROSS_CLASS_IOU
from services.detector.settings import DEFAULT_MODEL
from training.scene_dataset import render_scene_dataset

__all__ = [
    "GENERAL_MODEL",
    "TORCH_HINT",
    "OnboardOptions",
    "OnboardReport",
    "StageMinutes",
    "TorchMissingError",
    "default_work_dir",
    "idle_cores",
    "onboard_scene",
]

GENERAL_MODEL = DEFAULT_MODEL
VAL_SEED_OFFSET = 1000
TORCH_HINT = (
    'onboarding trains a model and needs PyTorch: pip install -e ".[train]" (torch==2.13.0, '
    "its CPU build: a plain torch requirement pulls a multi-GB CUDA one)"
)
# Rough costs on 2 CPU cores, only to weigh the stages in the progress fraction.
_RENDER_S_PER_IMAGE = 0.3
_TRAIN_S_PER_IMAGE = 0.025
_EVAL_S = 20.0

Progress = Callable[[str, float], None]


class TorchMissingError(RuntimeError):
    """PyTorch is not installed; the message says how to install it."""


@dataclass(frozen=True)
class OnboardOptions:
    """How much to render and train; the defaults fit a 6-object scene in about 5–6 minutes on
    2 CPU cores (see ``benchmarks/onboard.py``)."""

    train_images: int = 400
    val_images: int = 100
    epochs: int = 24
    max_minutes: float = 20.0
    """Wall-time cap of the whole run: training stops early (fewer epochs) to keep to it."""
    seed: int = 1
    threads: int | None = None
    """PyTorch threads; ``None``: the cores left idle by the load (:func:`idle_cores`)."""
    batch: int = 16
    lr: float = 1e-3

    def __post_init__(self) -> None:
        if min(self.train_images, self.val_images, self.epochs, self.threads or 1, self.batch) < 1:
            raise ValueError("images, epochs, threads and batch must be at least 1")
        if not (self.max_minutes > 0 and self.lr > 0):
            raise ValueError("max_minutes and lr must be positive")

    @classmethod
    def tiny(cls) -> OnboardOptions:
        """A CI-sized run (a few images, one epoch): checks the plumbing, not the accuracy."""
        return cls(train_images=8, val_images=4, epochs=1, batch=4)


@dataclass(frozen=True)
class StageMinutes:
    """Wall minutes per stage of this run (a resumed run counts only its own work)."""

    render: float
    train: float
    eval: float
    total: float


@dataclass(frozen=True)
class OnboardReport:
    """Where the model went and how well it does on held-out renders of its scene."""

    scene: str
    model_path: Path
    classes: tuple[str, ...]
    precision: float
    recall: float
    map50: float
    images: int
    val_images: int
    epochs: int
    minutes: StageMinutes
    per_class: dict[str, dict[str, float]] = field(default_factory=dict)


def default_work_dir(scene: LoadedScene) -> Path:
    """``data/onboard/<scene id>/`` (relative to the current folder)."""
    return Path("data") / "onboard" / scene.id


def idle_cores() -> int:
    """The cores not busy with other work: ``cores - round(1-minute load average)``, at least 1.

    On a shared machine this matters a lot: PyTorch's OpenMP threads spin while they wait for
    each other, and with more threads than idle cores a training step took 5-8 times as long
    (2 threads vs 1 at a load of 5 on 2 cores: 230-580 ms vs 43-70 ms per image).
    """
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # not available on this platform
        return cores
    return max(1, min(cores, cores - round(load)))


def _require_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError as exc:
        raise TorchMissingError(TORCH_HINT) from exc


VIEWS_RECIPE = "drone-views-1"
"""Changes when the views rendered change (:func:`~training.scene_dataset.scene_views`): a
dataset of the old views is rendered again, not reused."""


def _spec_digest(scene: LoadedScene) -> str:
    """Changes when anything rendered changes: the spec, an asset file's content or the views'
    recipe."""
    digest = hashlib.sha256((VIEWS_RECIPE + scene.spec.model_dump_json()).encode())
    for key in sorted(scene.assets):
        digest.update(key.encode() + scene.assets[key].read_bytes())
    return digest.hexdigest()[:12]


def _command(scene_path: Path, options: OnboardOptions, work_dir: Path | None) -> str:
    args = ["cosmos", "scenes", "add", str(scene_path)]
    default = OnboardOptions()
    for flag, name in (
        ("--images", "train_images"),
        ("--epochs", "epochs"),
        ("--seed", "seed"),
        ("--max-minutes", "max_minutes"),
    ):
        if getattr(options, name) != getattr(default, name):
            args += [flag, str(getattr(options, name))]
    if options.val_images != default.val_images:
        args += ["--val-images", str(options.val_images)]
    if work_dir is not None:
        args += ["--work", str(work_dir)]
    return shlex.join(args)


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def install_model(target: Path, onnx_bytes: bytes, sidecar: dict[str, Any], card: str) -> Path:
    """Install a model into ``target``: sidecar and card first, the ONNX file renamed into
    place last (each write atomic). Returns the model's path."""
    target.mkdir(parents=True, exist_ok=True)
    _write_atomic(target / SIDECAR_NAME, (json.dumps(sidecar, indent=2) + "\n").encode())
    _write_atomic(target / MODEL_CARD_NAME, card.encode())
    _write_atomic(target / MODEL_FILE_NAME, onnx_bytes)
    return target / MODEL_FILE_NAME


class _Clock:
    """Reports overall progress: each stage's share is its estimated cost."""

    def __init__(self, progress: Progress | None, weights: dict[str, float]) -> None:
        total = sum(weights.values())
        self._progress = progress
        self._start: dict[str, float] = {}
        acc = 0.0
        for stage, w in weights.items():
            self._start[stage] = acc / total
            acc += w
        self._share = {stage: w / total for stage, w in weights.items()}

    def __call__(self, stage: str, fraction: float) -> None:
        if self._progress is not None:
            done = self._start[stage] + self._share[stage] * min(1.0, max(0.0, fraction))
            self._progress(stage, done)


def _train(
    scene: LoadedScene,
    train_dir: Path,
    run_dir: Path,
    options: OnboardOptions,
    deadline: float,
    clock: _Clock,
) -> tuple[Any, int, int]:
    """Fine-tune; returns the averaged model, the epochs done and the training images."""
    import torch

    from training.data import load_dataset
    from training.model import anchor_points
    from training.train import INPUT_HEIGHT, INPUT_WIDTH, make_batch, save_checkpoint, train_step
    from training.warm_start import freeze_batchnorm, warm_start

    classes = object_classes(scene.spec)
    train = load_dataset(train_dir)
    model = warm_start(GENERAL_MODEL, [c.shape for c in classes])
    ema = copy.deepcopy(model).eval()
    optimizer = torch.optim.AdamW(model.parameters(), lr=options.lr, weight_decay=5e-4)
    steps_per_epoch = math.ceil(len(train) / options.batch)
    total_steps = options.epochs * steps_per_epoch
    warmup = max(1, min(30, total_steps // 10))

    def lr_at(step: int) -> float:
        if step < warmup:
            return options.lr * (step + 1) / warmup
        progress = (step - warmup) / max(1, total_steps - warmup)
        return options.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress)))

    start_epoch, step = 0, 0
    last = run_dir / "last.pt"
    if last.exists():
        state = torch.load(last, weights_only=False)
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        optimizer.load_state_dict(state["optimizer"])
        start_epoch, step = state["epoch"] + 1, state["step"]
    anchors = anchor_points(INPUT_HEIGHT, INPUT_WIDTH)
    epoch_s = 0.0
    epochs_done = start_epoch
    for epoch in range(start_epoch, options.epochs):
        if epoch > start_epoch and time.monotonic() + epoch_s > deadline:
            break  # the budget would be overrun: keep what is trained
        epoch_started = time.monotonic()
        model.train()
        freeze_batchnorm(model)
        rng = np.random.default_rng([options.seed, 7, epoch])
        order = rng.permutation(len(train))
        for first in range(0, len(order), options.batch):
            batch = make_batch([train[i] for i in order[first : first + options.batch]], rng)
            train_step(model, ema, optimizer, batch, anchors, lr_at(step), step)
            step += 1
            done = (epoch - start_epoch) * steps_per_epoch + first // options.batch + 1
            clock("train", done / max(1, (options.epochs - start_epoch) * steps_per_epoch))
        save_checkpoint(
            last,
            {
                "model": model.state_dict(),
                "ema": ema.state_dict(),
                "optimizer": optimizer.state_dict(),
                "epoch": epoch,
                "step": step,
                "classes": [c.label for c in classes],
            },
        )
        epoch_s = time.monotonic() - epoch_started
        epochs_done = epoch + 1
    return ema, epochs_done, len(train)


def onboard_scene(
    scene_path: Path,
    options: OnboardOptions = OnboardOptions(),  # noqa: B008 - frozen, so sharing it is safe
    *,
    work_dir: Path | None = None,
    progress: Progress | None = None,
) -> OnboardReport:
    """Train, evaluate and install the detector of the scene file ``scene_path``.

    ``progress(stage, fraction)`` hears the stage (``render``, ``train``, ``evaluate``) and the
    fraction of the whole run done. Raises :class:`~services.common.geometry.scene.SceneFileError`
    for an
    unusable scene (before rendering anything) and :class:`TorchMissingError` without PyTorch.
    """
    started = time.monotonic()
    deadline = started + 60 * options.max_minutes - _EVAL_S
    scene = load_scene(scene_path)
    _require_torch()
    import torch

    from training.card import scene_model_card
    from training.data import load_dataset
    from training.export import onnx_model, sidecar
    from training.train import INPUT_HEIGHT, INPUT_WIDTH, evaluate, torch_cpu

    threads = options.threads if options.threads is not None else idle_cores()
    classes = object_classes(scene.spec)
    labels = [c.label for c in classes]
    work = work_dir if work_dir is not None else default_work_dir(scene)
    digest = _spec_digest(scene)
    val_seed = options.seed + VAL_SEED_OFFSET
    train_dir = work / f"train-{digest}-s{options.seed}"
    val_dir = work / f"val-{digest}-s{val_seed}"
    run_dir = work / (
        f"run-{digest}-s{options.seed}-n{options.train_images}-e{options.epochs}"
        f"-b{options.batch}-lr{options.lr:g}"
    )
    run_dir.mkdir(parents=True, exist_ok=True)
    images = options.train_images + options.val_images
    clock = _Clock(
        progress,
        {
            "render": _RENDER_S_PER_IMAGE * images,
            "train": _TRAIN_S_PER_IMAGE * options.train_images * options.epochs,
            "evaluate": _EVAL_S,
        },
    )

    from services.renderer.engine import RenderEngine

    # Frozen recordings pay off for one repeated view; here the lighting changes every few views.
    engine = RenderEngine("auto", cache_size=2, freeze=False)
    engine.start()
    try:
        for out, count, seed in (
            (train_dir, options.train_images, options.seed),
            (val_dir, options.val_images, val_seed),
        ):
            before = options.train_images if out is val_dir else 0

            def rendered_so_far(done: int, before: int = before) -> None:
                clock("render", (before + done) / images)

            render_scene_dataset(engine, scene, out, count, seed, rendered_so_far)
    finally:
        engine.close()
    rendered = time.monotonic()

    with torch_cpu(threads):
        model, epochs, train_images = _train(scene, train_dir, run_dir, options, deadline, clock)
        trained = time.monotonic()

        clock("evaluate", 0.0)
        metrics = evaluate(
            model, load_dataset(val_dir), labels, cross_class_iou=SCENE_CROSS_CLASS_IOU
        )
        onnx_bytes, error = onnx_model(
            model,
            labels,
            INPUT_HEIGHT,
            INPUT_WIDTH,
            description=f"COSMOS 3D Search detector of scene {scene.id} (one class per object)",
        )
    finished = time.monotonic()
    minutes = StageMinutes(
        render=round((rendered - started) / 60, 2),
        train=round((trained - rendered) / 60, 2),
        eval=round((finished - trained) / 60, 2),
        total=round((finished - started) / 60, 2),
    )
    search = scene.spec.search
    info = {
        **sidecar(
            "model",
            labels,
            INPUT_WIDTH,
            INPUT_HEIGHT,
            onnx_bytes,
            sum(p.numel() for p in model.parameters()),
        ),
        "scene": scene.id,
        "provenance": {
            "trainer": "training.onboard (fine-tuned from the general model)",
            "torch": torch.__version__,
            "general_model_sha256": hashlib.sha256(GENERAL_MODEL.read_bytes()).hexdigest(),
            "scene_digest": digest,
            "export_max_abs_error": error,
            "onboarding": {
                **asdict(options),
                "threads": threads,
                "train_images": train_images,
                "val_images": options.val_images,
                "train_seed": options.seed,
                "val_seed": val_seed,
                "epochs": epochs,
                "film": [scene.spec.camera.width, scene.spec.camera.height],
                "theta_range_deg": [search.min_theta_deg, search.max_theta_deg],
                "minutes": asdict(minutes),
                "command": _command(scene_path, options, work_dir),
            },
            "validation": {
                k: round(float(metrics[k]), 4) for k in ("precision", "recall", "map50")
            },
        },
    }
    card = scene_model_card(
        info,
        metrics,
        [(c.label, c.objects) for c in classes],
        info["provenance"]["onboarding"]["command"],
    )
    path = install_model(model_dir(scene), onnx_bytes, info, card)
    clock("evaluate", 1.0)
    return OnboardReport(
        scene=scene.id,
        model_path=path,
        classes=tuple(labels),
        precision=float(metrics["precision"]),
        recall=float(metrics["recall"]),
        map50=float(metrics["map50"]),
        images=train_images,
        val_images=options.val_images,
        epochs=epochs,
        minutes=minutes,
        per_class=metrics["per_class"],
    )
