"""Loading a detector model: class names, sidecar, input size, provenance, and layout checks
that fail at start-up naming the file."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from services.detector.model import DetectorModel, ModelError, parse_names
from services.detector.synthetic import channel_mean_model, constant_model

PRED = np.array([[100.0], [120.0], [40.0], [60.0], [0.9], [0.1]], dtype=np.float32)


@pytest.fixture
def model_path(tmp_path):
    return constant_model(tmp_path / "det.onnx", PRED, classes=["sphere", "cube"])


def write_graph(path, inputs, outputs, nodes, names="{0: 'a'}"):
    graph = helper.make_graph(nodes, "g", inputs, outputs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"names": names})
    onnx.save(model, str(path))
    return path


def test_loads_names_size_and_hash_from_the_model(model_path):
    model = DetectorModel(model_path, threads=1)
    info = model.info
    assert info.name == "det"
    assert info.classes == ("sphere", "cube")
    assert info.input_size == (320, 320)
    assert info.sha256 == hashlib.sha256(model_path.read_bytes()).hexdigest()
    assert model.max_batch is None
    assert model.providers == ("CPUExecutionProvider",)


def test_runs_a_batch(model_path):
    model = DetectorModel(model_path, threads=1)
    out = model.run(np.zeros((3, 3, 320, 320), np.float32))
    assert out.shape == (3, 6, 1)
    np.testing.assert_allclose(out[2], PRED)
    with pytest.raises(ValueError, match="shape"):
        model.run(np.zeros((1, 3, 32, 32), np.float32))


def test_fixed_batch_models_run_image_by_image(tmp_path):
    path = channel_mean_model(tmp_path / "m.onnx", [5, 5, 2, 2], input_size=(64, 48), batch=1)
    model = DetectorModel(path, threads=1)
    assert model.max_batch == 1
    batch = np.zeros((3, 3, 48, 64), np.float32)
    batch[1, 0] = 1.0
    batch[2, 2] = 0.5
    out = model.run(batch)
    means = np.diagonal(out[:, 4:, :], axis1=1, axis2=2)  # anchor k, class k
    np.testing.assert_allclose(means, [[0, 0, 0], [1, 0, 0], [0, 0, 0.5]])


def test_float16_inputs_are_fed_float16(tmp_path):
    path = constant_model(tmp_path / "half.onnx", PRED, classes=["sphere", "cube"], half=True)
    model = DetectorModel(path, threads=1)
    assert model.layout.input_dtype is np.float16
    np.testing.assert_allclose(model.run(np.zeros((2, 3, 320, 320), np.float32))[1], PRED)


def test_sidecar_wins_and_carries_provenance(model_path):
    sidecar = {
        "classes": ["ball", "box"],
        "input_size": [320, 320],
        "name": "cosmos-yolo",
        "epochs": 40,
        "map50": 0.93,
        "dataset": "renders-v1",
        "augment": {"hsv": True},
        "final": True,
        "notes": None,
    }
    model_path.with_suffix(".json").write_text(json.dumps(sidecar))
    info = DetectorModel(model_path, threads=1).info
    assert info.name == "cosmos-yolo"
    assert info.classes == ("ball", "box")
    assert info.provenance == {
        "epochs": 40,
        "map50": 0.93,
        "dataset": "renders-v1",
        "augment": '{"hsv":true}',
        "final": "true",
    }


def test_ultralytics_metadata_becomes_provenance(tmp_path):
    path = constant_model(
        tmp_path / "u.onnx",
        PRED,
        classes=["sphere", "cube"],
        metadata={"author": "Ultralytics", "imgsz": "[320, 320]", "task": "detect"},
    )
    info = DetectorModel(path, threads=1).info
    assert info.provenance == {"author": "Ultralytics", "imgsz": "[320, 320]", "task": "detect"}


@pytest.mark.parametrize(
    ("text", "names"),
    [
        ("{0: 'sphere', 1: 'cube'}", ["sphere", "cube"]),
        ("{1: 'cube', 0: 'sphere'}", ["sphere", "cube"]),
        ('["sphere", "cube"]', ["sphere", "cube"]),
        ('{"0": "sphere", "1": "cube"}', ["sphere", "cube"]),
        ("['a']", ["a"]),
    ],
)
def test_parse_names(text, names):
    assert parse_names(text) == names


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os').system('true')",
        "{0: 'a', 2: 'b'}",
        "{'x': 'a'}",
        "[]",
        "[1, 2]",
        "'sphere'",
        "[''] ",
        "{0: 'a' * 100}",
        "not python",
    ],
)
def test_parse_names_rejects(text):
    with pytest.raises(ValueError, match="class name"):
        parse_names(text)


def test_missing_model_names_the_file(tmp_path):
    path = tmp_path / "nope.onnx"
    with pytest.raises(ModelError, match=str(path)):
        DetectorModel(path)


def test_garbage_file_names_the_file(tmp_path):
    path = tmp_path / "garbage.onnx"
    path.write_bytes(b"definitely not protobuf" * 10)
    with pytest.raises(ModelError, match="garbage.onnx.*not a loadable ONNX"):
        DetectorModel(path)


def test_class_count_must_match_the_output_channels(tmp_path):
    path = constant_model(tmp_path / "m.onnx", PRED, classes=["a", "b", "c"])
    with pytest.raises(ModelError, match=r"m\.onnx.*6 channels but 3 classes"):
        DetectorModel(path)


def test_sidecar_class_count_is_checked_too(model_path):
    model_path.with_suffix(".json").write_text(json.dumps({"classes": ["only"]}))
    with pytest.raises(ModelError, match="6 channels but 1 classes"):
        DetectorModel(model_path)


def test_a_transposed_output_is_refused(tmp_path):
    """(B, N, 4 + C), as some exports write it, is not the layout."""
    path = constant_model(tmp_path / "t.onnx", np.zeros((8400, 6), np.float32), classes=["a", "b"])
    with pytest.raises(ModelError, match="8400 channels"):
        DetectorModel(path)


def test_no_class_names_is_an_error(tmp_path):
    path = constant_model(tmp_path / "anon.onnx", PRED)
    with pytest.raises(ModelError, match="no class names.*anon.json"):
        DetectorModel(path)


@pytest.mark.parametrize(
    ("sidecar", "message"),
    [
        ("{not json", "not readable JSON"),
        ("[1, 2]", "JSON object"),
        ('{"classes": []}', "no class names"),
        ('{"classes": ["a", "b"], "input_size": [320]}', "input_size"),
        ('{"classes": ["a", "b"], "input_size": [256, 320]}', "differs"),
        ('{"classes": ["a", "b"], "name": 3}', "name"),
    ],
)
def test_bad_sidecars_name_the_sidecar(model_path, sidecar, message):
    model_path.with_suffix(".json").write_text(sidecar)
    with pytest.raises(ModelError, match=message) as caught:
        DetectorModel(model_path)
    assert "det.json" in str(caught.value) or "det.onnx" in str(caught.value)


def test_wrong_input_rank_is_refused(tmp_path):
    path = write_graph(
        tmp_path / "rank.onnx",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 64])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 64])],
        [helper.make_node("Identity", ["x"], ["y"])],
    )
    with pytest.raises(ModelError, match=r"rank\.onnx.*\(B, 3, H, W\)"):
        DetectorModel(path)


def test_wrong_output_rank_is_refused(tmp_path):
    path = write_graph(
        tmp_path / "flat.onnx",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])],
        [helper.make_node("ReduceMean", ["x"], ["y"], axes=[2, 3], keepdims=0)],
    )
    with pytest.raises(ModelError, match=r"flat\.onnx.*\(B, 4 \+ classes, N\)"):
        DetectorModel(path)


def test_integer_input_is_refused(tmp_path):
    path = write_graph(
        tmp_path / "int.onnx",
        [helper.make_tensor_value_info("x", TensorProto.UINT8, [1, 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.UINT8, [1, 3, 8, 8])],
        [helper.make_node("Identity", ["x"], ["y"])],
    )
    with pytest.raises(ModelError, match="float32 or float16 input"):
        DetectorModel(path)


def test_dynamic_input_size_needs_a_size(tmp_path):
    """A graph with dynamic height and width: refused without a size, served with one."""
    path = write_graph(
        tmp_path / "dyn.onnx",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["b", 3, "h", "w"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["b", 5, None])],
        [
            helper.make_node("ReduceMean", ["x"], ["m"], axes=[1], keepdims=1),  # (b, 1, h, w)
            helper.make_node(
                "Constant",
                [],
                ["s"],
                value=helper.make_tensor("s", TensorProto.INT64, [3], [0, 1, -1]),
            ),
            helper.make_node("Reshape", ["m", "s"], ["f"]),  # (b, 1, h*w)
            helper.make_node("Concat", ["f", "f", "f", "f", "f"], ["y"], axis=1),
        ],
    )
    with pytest.raises(ModelError, match="dynamic"):
        DetectorModel(path)
    path.with_suffix(".json").write_text(json.dumps({"classes": ["a"], "input_size": [64, 32]}))
    model = DetectorModel(path)
    assert model.info.input_size == (64, 32)
    assert model.run(np.zeros((2, 3, 32, 64), np.float32)).shape == (2, 5, 64 * 32)


def test_dynamic_output_channels_are_checked_by_a_test_inference(tmp_path):
    """Channels unknown until run time: the start-up inference catches the wrong count."""
    path = write_graph(
        tmp_path / "late.onnx",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "h", 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, None, 4])],
        [
            helper.make_node(
                "Constant",
                [],
                ["s"],
                value=helper.make_tensor("s", TensorProto.INT64, [3], [1, -1, 4]),
            ),
            helper.make_node("Reshape", ["x", "s"], ["y"]),
        ],
    )
    path.with_suffix(".json").write_text(json.dumps({"classes": ["a"], "input_size": [8, 8]}))
    with pytest.raises(
        ModelError, match=r"late\.onnx.*test inference gave an output of shape \[1, 48, 4\]"
    ):
        DetectorModel(path)


# -- settings ----------------------------------------------------------------------------------


def test_settings_come_from_cosmos_variables(monkeypatch, tmp_path):
    from services.detector.settings import DEFAULT_MODEL, DetectorSettings

    monkeypatch.delenv("COSMOS_DETECTOR_MODEL", raising=False)
    assert DetectorSettings().detector_model == DEFAULT_MODEL
    assert DEFAULT_MODEL.parts[-2:] == ("models", "detector.onnx")
    monkeypatch.setenv("COSMOS_DETECTOR_MODEL", str(tmp_path / "m.onnx"))
    monkeypatch.setenv("COSMOS_DETECTOR_CONF", "0.4")
    monkeypatch.setenv("COSMOS_DETECTOR_THREADS", "3")
    settings = DetectorSettings()
    assert settings.detector_model == tmp_path / "m.onnx"
    assert (settings.detector_conf, settings.detector_threads) == (0.4, 3)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("COSMOS_DETECTOR_CONF", "1.5"),
        ("COSMOS_DETECTOR_IOU", "0"),
        ("COSMOS_DETECTOR_MAX_BATCH", "0"),
        ("COSMOS_DETECTOR_MAX_IMAGE_PIXELS", str(2**40)),
        ("COSMOS_DETECTOR_THREADS", "-1"),
    ],
)
def test_nonsense_settings_fail_fast(monkeypatch, name, value):
    from pydantic import ValidationError

    from services.detector.settings import DetectorSettings

    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError):
        DetectorSettings()
