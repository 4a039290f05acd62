"""Model cards as Markdown: a scene's own detector's (``<id>.detector/MODEL_CARD.md``) and the
shipped general detector's (``models/MODEL_CARD.md``)."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from training.dataset import dataset_command

__all__ = ["model_rows", "scene_model_card", "write_general_card"]


def model_rows(sidecar: Mapping[str, Any]) -> list[str]:
    """The card's table rows that describe any model: classes, input, output, parameters."""
    return [
        "| | |",
        "| --- | --- |",
        f"| classes | {', '.join(sidecar['classes'])} |",
        f"| input | {sidecar['input_size'][0]}x{sidecar['input_size'][1]} RGB 0-1, centred "
        "letterbox, grey 114 |",
        f"| output | {sidecar.get('format', '')} |",
        f"| parameters | {sidecar.get('parameters', '?'):,} |",
    ]


def _row(name: str, m: Mapping[str, Any]) -> str:
    return (
        f"| {name} | {int(m['objects'])} | {float(m['precision']):.3f} | "
        f"{float(m['recall']):.3f} | {float(m.get('ap50', m.get('map50', 0.0))):.3f} |"
    )


def scene_model_card(
    sidecar: Mapping[str, Any],
    metrics: Mapping[str, Any],
    members: Sequence[tuple[str, Sequence[str]]],
    command: str,
) -> str:
    """The card: what the model detects, how it was trained and how well it does on held-out
    renders of its scene, and the command that makes it again.

    ``members`` pairs each class label with the object names it stands for.
    """
    onboarding = sidecar["provenance"]["onboarding"]
    minutes = onboarding["minutes"]
    per_class: Mapping[str, Mapping[str, Any]] = metrics["per_class"]
    lines = [
        f"# Model card: scene `{sidecar['scene']}` detector",
        "",
        f"The scene's own detector: one class per object of `{sidecar['scene']}` (objects that "
        "look alike share a class), fine-tuned from the general shape detector "
        "`models/detector.onnx` on renders of this scene alone (nothing downloaded). It is only "
        "meant for this scene.",
        "",
        *model_rows(sidecar),
        f"| sha256 | `{sidecar['sha256']}` |",
        f"| training data | {onboarding['train_images']} renders (seed {onboarding['train_seed']}"
        f"), film {onboarding['film'][0]}x{onboarding['film'][1]}, poses over "
        f"θ {onboarding['theta_range_deg'][0]}–{onboarding['theta_range_deg'][1]}° and all φ, "
        "a third drone views (any distance, mostly down, rolled, fov ±30 %), "
        "lighting jittered, spp 8/16/32 |",
        f"| training | {onboarding['epochs']} epochs from the general model, "
        f"{minutes['train']:.1f} min on {onboarding['threads']} CPU threads, "
        f"PyTorch {sidecar['provenance']['torch']} |",
        f"| wall time | render {minutes['render']:.1f} min, train {minutes['train']:.1f} min, "
        f"evaluate + export {minutes['eval']:.1f} min, total {minutes['total']:.1f} min |",
        "",
        "## Classes",
        "",
        "| class | objects |",
        "| --- | --- |",
        *(f"| {label} | {', '.join(names)} |" for label, names in members),
        "",
        f"## Accuracy on held-out renders ({onboarding['val_images']} images, seed "
        f"{onboarding['val_seed']}, never trained on)",
        "",
        "Objects at least 60 % visible, a hit at IoU >= 0.5, detections through the detector "
        "service's letterbox and post-processing (confidence 0.25, NMS 0.5).",
        "",
        "| class | objects | precision | recall | AP50 |",
        "| --- | --- | --- | --- | --- |",
        *(_row(label, per_class[label]) for label in sidecar["classes"]),
        _row("**overall** (mAP50)", metrics),
        "",
        "## Reproduce",
        "",
        "```sh",
        command,
        "```",
        "",
    ]
    return "\n".join(lines)


_GENERAL_GOALS = "precision >= 0.97 and recall >= 0.97 overall, box-centre error <= 2 px (median)"


_BASE_RECIPE = (
    ".venv/bin/python -m training.dataset --out data/train --count 4000 --seed 1",
    ".venv/bin/python -m training.dataset --out data/val --count 300 --seed 3",
    ".venv/bin/python -m training.train --data data/train --val data/val --run data/runs/w16 "
    "--epochs 24 --width 16",
    ".venv/bin/python -m training.export --checkpoint data/runs/w16/best.pt --out "
    "models/detector.onnx",
)


def _fine_tune_recipe(provenance: Mapping[str, Any]) -> list[str]:
    """The fine-tune's commands, from its provenance (its datasets are rendered by
    ``training.dataset``, with ``--drone-share`` for drone views; a model exported before the
    validation set was recorded names the base recipe's)."""
    data = " ".join(f"--data {d}" for d in provenance.get("datasets") or [])
    val = provenance.get("val_dataset") or "data/val"
    recipes: Mapping[str, Any] = provenance.get("dataset_recipes") or {}
    return [
        "# then the fine-tune from the model just exported",
        *(dataset_command(root, recipe) for root, recipe in recipes.items() if recipe),
        f".venv/bin/python -m training.train {data} --val {val} --run data/runs/tuned "
        f"--epochs {provenance.get('epochs')} --init models/detector.onnx",
        ".venv/bin/python -m training.export --checkpoint data/runs/tuned/best.pt --out "
        "models/detector.onnx",
    ]


def _training_rows(provenance: Mapping[str, Any]) -> list[str]:
    """The card's training rows: one run, or a base run and the fine-tune from it."""
    origin = provenance.get("fine_tuned_from")
    this = (
        f"{provenance.get('epochs')} epochs, {provenance.get('training_minutes')} minutes of "
        f"training steps on 2 shared CPU cores, PyTorch {provenance.get('torch')}"
    )
    if not origin:
        return [f"| training | {this} |"]
    base = origin.get("provenance") or {}
    return [
        f"| base model | `{origin['sha256'][:16]}…`: {base.get('train_images')} rendered "
        f"hemisphere views, {base.get('epochs')} epochs, {base.get('training_minutes')} minutes |",
        f"| fine-tune | from the base model, BatchNorms fixed: {this} |",
    ]


def write_general_card(card: Path, model: Path, report: Mapping[str, Any], table: str) -> None:
    """Write the shipped general detector's card to ``card``: its sidecar beside ``model``,
    and the held-out figures of a ``python -m benchmarks.detector --card`` run (``report``,
    and ``table`` as printed), so no number on it is typed by hand."""
    sidecar = json.loads(model.with_suffix(".json").read_text())
    provenance = sidecar.get("provenance", {})
    met = (
        report["precision"] >= 0.97
        and report["recall"] >= 0.97
        and report["centre_error_median_px"] <= 2.0
    )
    lines = [
        f"# Model card: `{model.name}`",
        "",
        "A small anchor-free, YOLO-style detector of the scene objects' shape classes, trained by",
        "this project on images rendered by its own renderer (nothing downloaded).",
        "",
        *model_rows(sidecar),
        f"| file | {model.stat().st_size:,} bytes, sha256 `{sidecar['sha256'][:16]}…` |",
        f"| training data | {provenance.get('train_images')} rendered images, datasets "
        f"{provenance.get('datasets')} |",
        *_training_rows(provenance),
        "",
        "## Accuracy on held-out renders",
        "",
        f"Measured {datetime.now(UTC):%Y-%m-%d} by `python -m benchmarks.detector --card "
        f"{card.as_posix()}` (seed {report['seed']}, never used for training):",
        "",
        "```",
        table,
        "```",
        "",
        f"Goals: {_GENERAL_GOALS} — {'met' if met else 'not met'} in this run.",
        "",
        "## Reproduce",
        "",
        "```sh",
        *_BASE_RECIPE,
        *(_fine_tune_recipe(provenance) if provenance.get("fine_tuned_from") else ()),
        f".venv/bin/python -m benchmarks.detector --card {card.as_posix()}",
        "```",
        "",
    ]
    card.write_text("\n".join(lines))
