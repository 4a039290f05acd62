"""The detector model: one onnxruntime session, its class names, input size and provenance.

A model is any YOLO-format ONNX file (Ultralytics' YOLOv8/YOLO11 export is one):

- one input ``(B, 3, H, W)``, float32 (or float16) RGB in [0, 1]; ``B`` fixed or dynamic, ``H``
  and ``W`` fixed (or, if dynamic, given by the sidecar's ``input_size`` or the ``imgsz``
  metadata);
- its first output ``(B, 4 + C, N)``: per anchor ``cx, cy, w, h`` in input pixels, then C class
  scores in [0, 1];
- class names from the sidecar ``<model>.json`` (``{"classes": [...], "input_size": [w, h],
  "name": ..., ...provenance}``) or else from the ONNX metadata key ``names`` (a Python dict
  literal ``{0: 'sphere', ...}`` as Ultralytics writes it, or a JSON list).

Everything is checked when the model is loaded, including one inference on a blank input, so a
wrong file fails at start-up with :class:`ModelError` naming it, not on the first request.
"""

from __future__ import annotations

import ast
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from services.common.contracts.detect import ModelInfo

__all__ = ["DetectorModel", "ModelError", "ModelLayout", "parse_names"]

_MAX_LABEL = 64  # Detection.label's limit
_INPUT_TYPES: dict[str, type[np.floating[Any]]] = {
    "tensor(float)": np.float32,
    "tensor(float16)": np.float16,
}


class ModelError(RuntimeError):
    """The model cannot be served: missing, unreadable, or not of the YOLO layout."""


@dataclass(frozen=True)
class ModelLayout:
    """The tensors of a validated model."""

    input_name: str
    output_name: str
    input_size: tuple[int, int]
    """Network input (width, height) in pixels."""
    batch: int | None
    """The fixed batch size, or None when the batch dimension is dynamic."""
    num_classes: int
    input_dtype: type[np.floating[Any]]


def parse_names(text: str) -> list[str]:
    """Class names from metadata: a JSON list, or a dict ``{0: 'a', 1: 'b'}`` (Python literal or
    JSON) whose keys are 0..C-1. Parsed with :func:`ast.literal_eval`, never ``eval``."""
    value: object
    try:
        value = json.loads(text)
    except ValueError:
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError) as exc:
            raise ValueError(f"class names are neither JSON nor a Python literal: {exc}") from exc
    if isinstance(value, dict):
        try:
            keyed = {int(key): name for key, name in value.items()}
        except (TypeError, ValueError) as exc:
            raise ValueError("class name keys must be integers") from exc
        if sorted(keyed) != list(range(len(keyed))):
            raise ValueError("class name keys must be 0..C-1")
        value = [keyed[i] for i in range(len(keyed))]
    if not isinstance(value, list | tuple):
        raise ValueError("class names must be a list or a dict")
    return _check_names(list(value))


def _check_names(names: list[object]) -> list[str]:
    if not names:
        raise ValueError("there are no class names")
    for name in names:
        if not isinstance(name, str) or not 1 <= len(name) <= _MAX_LABEL:
            raise ValueError(f"class names must be strings of 1-{_MAX_LABEL} characters: {name!r}")
    return [str(name) for name in names]


def _provenance_value(value: object) -> str | int | float | None:
    if value is None:
        return None
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float | str):
        return value
    return json.dumps(value, separators=(",", ":"), sort_keys=True)


@dataclass(frozen=True)
class _Sidecar:
    classes: list[str]
    input_size: tuple[int, int] | None
    name: str | None
    provenance: dict[str, str | int | float]


def _read_sidecar(path: Path) -> _Sidecar | None:
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ModelError(f"model sidecar {path} is not readable JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ModelError(f"model sidecar {path} must hold a JSON object")
    try:
        classes = _check_names(data.get("classes") or [])
    except ValueError as exc:
        raise ModelError(f"model sidecar {path}: classes: {exc}") from exc
    size = data.get("input_size")
    input_size: tuple[int, int] | None = None
    if size is not None:
        if (
            not isinstance(size, list)
            or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
        ):
            raise ModelError(f"model sidecar {path}: input_size must be [width, height]")
        input_size = (size[0], size[1])
    name = data.get("name")
    if name is not None and not isinstance(name, str):
        raise ModelError(f"model sidecar {path}: name must be a string")
    provenance = {
        key: converted
        for key, value in data.items()
        if key not in {"classes", "input_size", "name"}
        and (converted := _provenance_value(value)) is not None
    }
    return _Sidecar(classes, input_size, name, provenance)


def _static(dim: object) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


class DetectorModel:
    """An onnxruntime session over a validated YOLO-format model (``scene``: the scene it was
    onboarded for, None for the general model).

    :meth:`run` is safe to call from any thread (onnxruntime releases the GIL); the service calls
    it from one worker thread so that one batch uses all ``threads``.
    """

    def __init__(self, path: Path, *, threads: int = 0, scene: str | None = None) -> None:
        self.path = path = Path(path)
        if not path.is_file():
            raise ModelError(
                f"detector model {path} does not exist (set COSMOS_DETECTOR_MODEL to a YOLO ONNX)"
            )
        try:
            content = path.read_bytes()
        except OSError as exc:
            raise ModelError(f"detector model {path} is not readable: {exc}") from exc
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        # Threads sleep between runs instead of spinning: the service shares its cores.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self._session = ort.InferenceSession(
                content, sess_options=options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise ModelError(f"detector model {path} is not a loadable ONNX model: {exc}") from exc
        self.threads = threads
        self.providers: tuple[str, ...] = tuple(self._session.get_providers())
        metadata: dict[str, str] = dict(self._session.get_modelmeta().custom_metadata_map)
        sidecar = _read_sidecar(path.with_suffix(".json"))
        self.classes = self._class_names(metadata, sidecar)
        self.layout = self._validate(metadata, sidecar, len(self.classes))
        provenance: dict[str, str | int | float] = {
            key: value for key, value in metadata.items() if key != "names"
        }
        if sidecar is not None:
            provenance.update(sidecar.provenance)
        self.info = ModelInfo(
            name=(sidecar.name if sidecar and sidecar.name else path.stem),
            classes=tuple(self.classes),
            input_size=self.layout.input_size,
            sha256=hashlib.sha256(content).hexdigest(),
            provenance=provenance,
            scene=scene,
        )
        self._warm_up()

    # -- loading -----------------------------------------------------------------------------

    def _fail(self, detail: str) -> ModelError:
        return ModelError(f"detector model {self.path}: {detail}")

    def _class_names(self, metadata: dict[str, str], sidecar: _Sidecar | None) -> list[str]:
        if sidecar is not None:
            return sidecar.classes
        if "names" in metadata:
            try:
                return parse_names(metadata["names"])
            except ValueError as exc:
                raise self._fail(f"metadata 'names': {exc}") from exc
        raise self._fail(
            f"no class names: add a sidecar {self.path.with_suffix('.json').name} with "
            "'classes', or ONNX metadata 'names'"
        )

    def _validate(
        self, metadata: dict[str, str], sidecar: _Sidecar | None, num_classes: int
    ) -> ModelLayout:
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1:
            raise self._fail(f"expected one input (B, 3, H, W), found {len(inputs)}")
        tensor = inputs[0]
        shape = list(tensor.shape)
        if len(shape) != 4 or _static(shape[1]) != 3:
            raise self._fail(f"expected an input of shape (B, 3, H, W), found {shape}")
        dtype = _INPUT_TYPES.get(tensor.type)
        if dtype is None:
            raise self._fail(f"expected a float32 or float16 input, found {tensor.type}")
        # an output of unknown rank (reported as []) is left to the test inference
        if not outputs or len(outputs[0].shape) not in (0, 3):
            found = outputs[0].shape if outputs else "none"
            raise self._fail(f"expected an output of shape (B, 4 + classes, N), found {found}")

        height, width = _static(shape[2]), _static(shape[3])
        if width is not None and height is not None:
            input_size = (width, height)
            if sidecar and sidecar.input_size and sidecar.input_size != input_size:
                raise self._fail(
                    f"the sidecar's input_size {list(sidecar.input_size)} differs from the "
                    f"model's input (width, height) {list(input_size)}"
                )
        elif sidecar and sidecar.input_size:
            input_size = sidecar.input_size
        elif "imgsz" in metadata:  # Ultralytics writes [h, w]
            try:
                h, w = (int(v) for v in ast.literal_eval(metadata["imgsz"]))
            except (ValueError, SyntaxError, TypeError) as exc:
                raise self._fail(f"metadata 'imgsz' is not [h, w]: {exc}") from exc
            input_size = (w, h)
        else:
            raise self._fail(
                f"the input's height and width are dynamic ({shape}) and no input_size is given"
            )

        channels = _static(outputs[0].shape[1]) if outputs[0].shape else None
        if channels is not None and channels != 4 + num_classes:
            raise self._fail(
                f"the output {list(outputs[0].shape)} has {channels} channels but "
                f"{num_classes} classes need 4 + {num_classes}; expected (B, 4 + classes, N)"
            )
        return ModelLayout(
            input_name=tensor.name,
            output_name=outputs[0].name,
            input_size=input_size,
            batch=_static(shape[0]),
            num_classes=num_classes,
            input_dtype=dtype,
        )

    def _warm_up(self) -> None:
        """One run on a blank input: checks the output's real shape and pays the first-run cost."""
        w, h = self.layout.input_size
        batch = self.layout.batch or 1
        try:
            out = self._run_exact(np.zeros((batch, 3, h, w), dtype=np.float32))
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise self._fail(f"a test inference failed: {exc}") from exc
        if out.ndim != 3 or out.shape[0] != batch or out.shape[1] != 4 + self.layout.num_classes:
            raise self._fail(
                f"a test inference gave an output of shape {list(out.shape)}; expected "
                f"({batch}, {4 + self.layout.num_classes}, N)"
            )

    # -- inference ---------------------------------------------------------------------------

    @property
    def max_batch(self) -> int | None:
        """Images one run can take: the fixed batch size, or None when it is dynamic."""
        return self.layout.batch

    def _run_exact(self, batch: NDArray[np.float32]) -> NDArray[np.float32]:
        feed = {self.layout.input_name: batch.astype(self.layout.input_dtype, copy=False)}
        (out,) = self._session.run([self.layout.output_name], feed)
        result: NDArray[np.float32] = np.asarray(out, dtype=np.float32)
        return result

    def run(self, batch: NDArray[np.float32]) -> NDArray[np.float32]:
        """Raw outputs ``(B, 4 + C, N)`` for inputs ``(B, 3, H, W)`` in [0, 1].

        A model with a fixed batch size b is run on chunks of b (the last one zero-padded).
        """
        w, h = self.layout.input_size
        if batch.ndim != 4 or batch.shape[1:] != (3, h, w):
            raise ValueError(f"expected inputs of shape (B, 3, {h}, {w}), got {batch.shape}")
        fixed = self.layout.batch
        if fixed is None or fixed == batch.shape[0]:
            return self._run_exact(batch)
        count = batch.shape[0]
        outputs = []
        for start in range(0, count, fixed):
            chunk = batch[start : start + fixed]
            if chunk.shape[0] < fixed:
                pad = np.zeros((fixed - chunk.shape[0], 3, h, w), dtype=batch.dtype)
                chunk = np.concatenate([chunk, pad])
            outputs.append(self._run_exact(chunk))
        return np.concatenate(outputs)[:count]
