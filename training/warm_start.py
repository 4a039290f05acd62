"""Start a scene's detector from the shipped general model's ONNX weights.

The exported graph keeps PyTorch's parameter names (prefixed ``model.``) with each BatchNorm
folded into the conv before it: for a conv weight ``W`` and a BatchNorm ``(γ, β, μ, σ², ε)``,

    W' = W · γ / sqrt(σ² + ε)        b' = β - μ · γ / sqrt(σ² + ε)

stored as ``<conv>.weight`` (``W'``) and ``<conv>.weight_bias`` (``b'``). Loading ``W' `` into the
conv and setting the BatchNorm to ``γ = 1, β = b', μ = 0, σ² = 1 - ε`` gives back the same
function exactly (the BatchNorm divides by ``sqrt(σ² + ε) = 1``). The head's last convs
(``heads.K.box.2``, ``heads.K.cls.2``) are plain convs with their own bias.

The class branch's last conv gets one output row per scene class. Each row starts from the
general model's row for the class's shape (``sphere`` … ``mesh``): the fine-tune then only has
to tell apart objects of the same shape, not find objects from scratch.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
import torch
from numpy.typing import NDArray
from onnx import numpy_helper
from torch import nn

from training.dataset import CLASSES
from training.model import Detector

__all__ = ["freeze_batchnorm", "general_weights", "warm_start"]

_PREFIX = "model."


def general_weights(onnx_path: Path) -> dict[str, NDArray[np.float32]]:
    """The ONNX file's initializers that are model parameters, by PyTorch name (no prefix)."""
    graph = onnx.load(str(onnx_path)).graph
    return {
        init.name[len(_PREFIX) :]: np.array(numpy_helper.to_array(init), dtype=np.float32)
        for init in graph.initializer
        if init.name.startswith(_PREFIX)
    }


def _width(weights: dict[str, NDArray[np.float32]]) -> int:
    """The ``width`` the general model was built with (its stem's first conv has width / 2)."""
    return 2 * int(weights["stem.0.0.weight"].shape[0])


def warm_start(
    onnx_path: Path, class_shapes: Sequence[str], general_classes: Sequence[str] = CLASSES
) -> Detector:
    """A detector for ``len(class_shapes)`` classes holding the general model's weights.

    ``class_shapes[k]`` is the shape of scene class ``k`` (one of ``general_classes``); its class
    row starts as that shape's row of the general model.
    """
    weights = general_weights(onnx_path)
    model = Detector(len(class_shapes), _width(weights))
    rows = [list(general_classes).index(shape) for shape in class_shapes]
    state = model.state_dict()
    loaded: set[str] = set()
    with torch.no_grad():
        for name, module in model.named_modules():
            if isinstance(module, nn.Conv2d):
                weight = weights[f"{name}.weight"]
                if name.endswith("cls.2"):
                    weight = weight[rows]
                state[f"{name}.weight"].copy_(torch.from_numpy(weight))
                loaded.add(f"{name}.weight")
                if module.bias is not None:
                    bias = weights[f"{name}.bias"]
                    if name.endswith("cls.2"):
                        bias = bias[rows]
                    state[f"{name}.bias"].copy_(torch.from_numpy(bias))
                    loaded.add(f"{name}.bias")
            elif isinstance(module, nn.BatchNorm2d):
                conv = name[: -len("1")] + "0"  # ConvBnAct: the conv is item 0, the norm item 1
                folded = torch.from_numpy(weights[f"{conv}.weight_bias"])
                state[f"{name}.weight"].fill_(1.0)
                state[f"{name}.bias"].copy_(folded)
                state[f"{name}.running_mean"].zero_()
                state[f"{name}.running_var"].fill_(1.0 - module.eps)
                loaded.update(
                    f"{name}.{p}" for p in ("weight", "bias", "running_mean", "running_var")
                )
    missing = [k for k, v in state.items() if k not in loaded and v.is_floating_point()]
    if missing:
        raise ValueError(f"{onnx_path}: no weights for {missing[:5]}")
    return model


def freeze_batchnorm(model: nn.Module) -> None:
    """Keep every BatchNorm in eval mode (fixed statistics) while the rest trains: a short
    fine-tune on one scene's images would otherwise drag the statistics away from the general
    model's; the affine ``γ, β`` still learn."""
    for module in model.modules():
        if isinstance(module, nn.BatchNorm2d):
            module.eval()
