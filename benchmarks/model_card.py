"""Write the shipped detector's model card from its sidecar and a benchmark run (no hand-typed
numbers)."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from training.card import model_rows

__all__ = ["write_card"]

GOALS = "precision >= 0.97 and recall >= 0.97 overall, box-centre error <= 2 px (median)"


def write_card(card: Path, model: Path, report: dict[str, Any], table: str) -> None:
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
        f"| training | {provenance.get('epochs')} epochs, {provenance.get('training_minutes')} "
        f"minutes of training steps on 2 shared CPU cores, PyTorch {provenance.get('torch')} |",
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
        f"Goals: {GOALS} — {'met' if met else 'not met'} in this run.",
        "",
        "## Reproduce",
        "",
        "```sh",
        ".venv/bin/python -m training.dataset --out data/train --count 4000 --seed 1",
        ".venv/bin/python -m training.dataset --out data/val --count 300 --seed 3",
        ".venv/bin/python -m training.train --data data/train --val data/val --run data/runs/w16 "
        "--epochs 24 --width 16",
        ".venv/bin/python -m training.export --checkpoint data/runs/w16/best.pt --out "
        "models/detector.onnx",
        f".venv/bin/python -m benchmarks.detector --card {card.as_posix()}",
        "```",
        "",
    ]
    card.write_text("\n".join(lines))
