"""Export a trained checkpoint to the ONNX model the detector service runs, with its sidecar.

Run ``python -m training.export --checkpoint data/runs/v1/best.pt --out models/detector.onnx``.
The graph takes ``images`` (N x 3 x 256 x 320, RGB 0–1, dynamic batch) and outputs ``output0``
``[N, 4 + C, anchors]`` — (cx, cy, w, h) in input pixels, then per-class scores — the layout of
Ultralytics' YOLOv8 export. Class names go into the ONNX metadata (``names``, Ultralytics style)
and into ``<out>.json`` with the provenance. The export is checked against PyTorch with
onnxruntime before it is written.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch

from services.detector.letterbox import PAD_VALUE
from training.model import Detector, ExportWrapper

__all__ = ["DESCRIPTION", "export", "main", "onnx_model", "sidecar"]

DESCRIPTION = "COSMOS 3D Search shape detector (trained on renders of the project)"


def _onnx_export(wrapper: torch.nn.Module, dummy: torch.Tensor, path: Path) -> None:
    """torch.export-based ONNX export with a dynamic batch dimension."""
    torch.onnx.export(
        wrapper,
        (dummy,),
        str(path),
        input_names=["images"],
        output_names=["output0"],
        dynamic_shapes={"images": {0: torch.export.Dim("batch", min=1, max=256)}},
        opset_version=18,
        dynamo=True,
        external_data=False,
        verbose=False,
    )


def onnx_model(
    model: Detector, classes: Sequence[str], height: int, width: int, description: str = DESCRIPTION
) -> tuple[bytes, float]:
    """The serialised ONNX graph of ``model`` (class names and input size in its metadata) and
    its largest absolute difference from PyTorch on random input, checked with onnxruntime."""
    wrapper = ExportWrapper(model, height, width).eval()
    dummy = torch.rand(2, 3, height, width)
    with tempfile.TemporaryDirectory() as tmp:
        raw_path = Path(tmp) / "model.onnx"
        with warnings.catch_warnings():
            # torch's own exporter trips over its own deprecations; nothing here to act on.
            warnings.simplefilter("ignore", category=FutureWarning)
            warnings.simplefilter("ignore", category=DeprecationWarning)
            _onnx_export(wrapper, dummy, raw_path)
        graph = onnx.load(str(raw_path))
    metadata = {
        "names": repr(dict(enumerate(classes))),
        "imgsz": json.dumps([height, width]),
        "stride": "32",
        "task": "detect",
        "description": description,
    }
    for key, value in metadata.items():
        entry = graph.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(graph)
    data = graph.SerializeToString()

    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    probe = torch.rand(3, 3, height, width)
    with torch.no_grad():
        expected = wrapper(probe).numpy()
    got = session.run(None, {"images": probe.numpy()})[0]
    error = float(np.abs(got - expected).max())
    if error > 1e-2:
        raise RuntimeError(f"ONNX output differs from PyTorch by {error}")
    return data, error


def sidecar(
    name: str, classes: Sequence[str], width: int, height: int, data: bytes, parameters: int
) -> dict[str, Any]:
    """The sidecar fields every model shares (``provenance`` is the caller's)."""
    return {
        "name": name,
        "classes": list(classes),
        "input_size": [width, height],
        "format": "yolov8-onnx: output0 [N, 4 + C, anchors] = cx, cy, w, h (input px), scores",
        "letterbox": {"pad_value": PAD_VALUE, "placement": "centred"},
        "sha256": hashlib.sha256(data).hexdigest(),
        "parameters": parameters,
    }


def export(checkpoint: Path, out: Path, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``out`` (ONNX) and ``out.with_suffix('.json')`` (sidecar); return the sidecar."""
    state = torch.load(checkpoint, weights_only=False)
    config = state["config"]
    classes = list(config["classes"])
    width, height = config["input"]
    model = Detector(len(classes), config["width"])
    model.load_state_dict(state["ema"])
    data, error = onnx_model(model, classes, height, width)

    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    history = state.get("history", [])
    info = {
        **sidecar(
            out.stem, classes, width, height, data, sum(p.numel() for p in model.parameters())
        ),
        "provenance": {
            "trainer": "training.train (plain PyTorch, task-aligned assignment, GIoU + BCE)",
            "torch": torch.__version__,
            "epochs": len(history),
            "train_images": state.get("train_images"),
            "datasets": state.get("data"),
            "val_dataset": state.get("val"),
            "dataset_recipes": state.get("recipes"),
            "training_minutes": round(sum(h["epoch_s"] for h in history) / 60, 1),
            "validation": history[-1] if history else None,
            **({"fine_tuned_from": state["init"]} if state.get("init") else {}),
            "export_max_abs_error": error,
            **(extra or {}),
        },
    }
    out.with_suffix(".json").write_text(json.dumps(info, indent=2) + "\n")
    return info


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("models/detector.onnx"))
    args = parser.parse_args(argv)
    info = export(args.checkpoint, args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes) and {args.out.with_suffix('.json')}")
    print(json.dumps(info["provenance"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
