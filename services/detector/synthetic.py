"""Tiny YOLO-layout ONNX models with known outputs, for tests and for running the service without a
trained model. Needs the ``onnx`` package (the ``dev`` extra).

- :func:`constant_model` always predicts the given ``(4 + C, N)`` tensor, whatever the image;
- :func:`channel_mean_model` predicts one fixed box three times, scored for class k with the mean
  of input channel k, which shows exactly what the network was fed (padding, channel order,
  scaling).

Both take a dynamic batch dimension unless ``batch`` is a number.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx
from numpy.typing import ArrayLike
from onnx import TensorProto, helper, numpy_helper

__all__ = ["channel_mean_model", "constant_model"]

_OPSET = 17
_IR_VERSION = 8  # old enough for any onnxruntime >= 1.14


def _names_literal(classes: Sequence[str]) -> str:
    """Ultralytics' way of writing class names into the metadata: a Python dict literal."""
    return repr(dict(enumerate(classes)))


def _save(
    path: Path,
    nodes: list[onnx.NodeProto],
    initializers: list[onnx.TensorProto],
    input_size: tuple[int, int],
    output_channels: int,
    batch: int | str,
    classes: Sequence[str] | None,
    metadata: Mapping[str, str] | None,
    input_type: int = TensorProto.FLOAT,
) -> Path:
    width, height = input_size
    graph = helper.make_graph(
        nodes,
        "synthetic_yolo",
        [helper.make_tensor_value_info("images", input_type, [batch, 3, height, width])],
        [
            helper.make_tensor_value_info(
                "output0", TensorProto.FLOAT, [batch, output_channels, None]
            )
        ],
        initializer=initializers,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", _OPSET)], producer_name="cosmos-synthetic"
    )
    model.ir_version = _IR_VERSION
    props = dict(metadata or {})
    if classes is not None:
        props.setdefault("names", _names_literal(classes))
    if props:
        helper.set_model_props(model, props)
    onnx.checker.check_model(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def _batch_shape_nodes(
    tail: Sequence[int], out: str
) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """Nodes computing the int64 shape ``[B, *tail]`` of the input's batch size ``B``."""
    inits = [
        numpy_helper.from_array(np.array([0], dtype=np.int64), f"{out}_start"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), f"{out}_end"),
        numpy_helper.from_array(np.array(tail, dtype=np.int64), f"{out}_tail"),
    ]
    nodes = [
        helper.make_node("Shape", ["images"], [f"{out}_shape"]),
        helper.make_node("Slice", [f"{out}_shape", f"{out}_start", f"{out}_end"], [f"{out}_b"]),
        helper.make_node("Concat", [f"{out}_b", f"{out}_tail"], [out], axis=0),
    ]
    return nodes, inits


def constant_model(
    path: Path,
    predictions: ArrayLike,
    *,
    input_size: tuple[int, int] = (320, 320),
    classes: Sequence[str] | None = None,
    batch: int | str = "batch",
    metadata: Mapping[str, str] | None = None,
    half: bool = False,
) -> Path:
    """Write a model whose output for every image is ``predictions`` ``(4 + C, N)``.

    ``input_size`` is (width, height); ``classes`` go into the metadata key ``names`` as
    Ultralytics writes it (leave them out to test a sidecar or their absence); ``half`` makes
    the input float16, like a ``half=True`` export.
    """
    pred = np.asarray(predictions, dtype=np.float32)
    if pred.ndim != 2:
        raise ValueError(f"predictions must be (4 + C, N), got {pred.shape}")
    shape_nodes, inits = _batch_shape_nodes(pred.shape, "target")
    inits.append(numpy_helper.from_array(pred[None], "prediction"))
    nodes = [*shape_nodes, helper.make_node("Expand", ["prediction", "target"], ["output0"])]
    input_type = TensorProto.FLOAT16 if half else TensorProto.FLOAT
    return _save(
        path, nodes, inits, input_size, pred.shape[0], batch, classes, metadata, input_type
    )


def channel_mean_model(
    path: Path,
    box_cxcywh: Sequence[float],
    *,
    input_size: tuple[int, int] = (320, 320),
    classes: Sequence[str] = ("red", "green", "blue"),
    batch: int | str = "batch",
) -> Path:
    """Write a model with three anchors at one box ``(cx, cy, w, h)`` (input pixels): anchor k
    scores class k with the mean of input channel k over the whole tensor, the others with 0."""
    if len(classes) != 3:
        raise ValueError("the channel-mean model has exactly three classes")
    shape_nodes, inits = _batch_shape_nodes([4, 3], "box_shape")
    boxes = np.repeat(np.asarray(box_cxcywh, dtype=np.float32).reshape(1, 4, 1), 3, axis=2)
    inits += [
        numpy_helper.from_array(boxes, "box"),
        numpy_helper.from_array(np.eye(3, dtype=np.float32)[None], "eye"),
        numpy_helper.from_array(np.array([2], dtype=np.int64), "anchor_axis"),
    ]
    nodes = [
        *shape_nodes,
        helper.make_node("Expand", ["box", "box_shape"], ["boxes"]),  # (B, 4, 3)
        helper.make_node("ReduceMean", ["images"], ["means"], axes=[2, 3], keepdims=0),  # (B, 3)
        helper.make_node("Unsqueeze", ["means", "anchor_axis"], ["column"]),  # (B, 3, 1)
        helper.make_node("Mul", ["column", "eye"], ["scores"]),  # (B, 3, 3): diagonal
        helper.make_node("Concat", ["boxes", "scores"], ["output0"], axis=1),  # (B, 7, 3)
    ]
    return _save(path, nodes, inits, input_size, 7, batch, classes, None)
