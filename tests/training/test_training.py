"""The detector's training tools: dataset rendering, augmentation, metrics, loss and export."""

from __future__ import annotations

import ast
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.geometry.scene import SceneSpec
from training.data import LabelledImage, augment, load_dataset
from training.dataset import CLASSES, TEXTURES, random_scene, render_dataset, views
from training.metrics import Evaluation, box_iou


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_random_scenes_are_valid_and_do_not_pile_up(seed):
    spec = random_scene(np.random.default_rng(seed), TEXTURES)
    assert isinstance(spec, SceneSpec)
    assert 1 <= len(spec.objects) <= 10
    assert {o.shape for o in spec.objects} <= set(CLASSES)
    centres = np.array([o.position for o in spec.objects])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.eye(len(centres)) * 99
    assert gaps.min() > 0.1  # touching is allowed, stacking is not


def test_views_are_reproducible_and_seeds_differ(tmp_path):
    first = [(v.scene.id, v.pose, v.width, v.spp, v.seed) for v in views(tmp_path, 5, 12)]
    again = [(v.scene.id, v.pose, v.width, v.spp, v.seed) for v in views(tmp_path, 5, 12)]
    other = [(v.scene.id, v.pose, v.width, v.spp, v.seed) for v in views(tmp_path, 6, 12)]
    assert first == again
    assert first != other
    assert [v for v in first if v[0].startswith("s")], "no random scene among 12 views"


def test_rendered_dataset_matches_the_renderer_ground_truth(tmp_path):
    assert render_dataset(tmp_path, count=4, seed=11) == 4
    assert render_dataset(tmp_path, count=4, seed=11) == 0  # resumes: nothing left to do
    samples = load_dataset(tmp_path)
    assert len(samples) == 4
    for label in sorted((tmp_path / "labels").glob("*.json")):
        meta = json.loads(label.read_text())
        for obj in meta["objects"]:
            x1, y1, x2, y2 = obj["box"]
            assert 0 <= x1 < x2 <= meta["width"]
            assert 0 <= y1 < y2 <= meta["height"]
            assert CLASSES[obj["class_id"]] == obj["class"]
            assert 0 < obj["visible_fraction"] <= 1


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_augmented_boxes_stay_on_the_canvas_and_on_their_objects(seed):
    rng = np.random.default_rng(seed)
    image = np.full((240, 320, 3), 60, np.uint8)
    image[50:90, 100:160] = (250, 20, 20)
    sample = LabelledImage(
        rgb=image,
        boxes=np.array([[100, 50, 160, 90]], np.float32),
        classes=np.array([2]),
        visible=np.array([1.0], np.float32),
        scene="t",
    )
    canvas, boxes, classes = augment(sample, 320, 256, rng)
    assert canvas.shape == (256, 320, 3)
    for (x1, y1, x2, y2), c in zip(boxes, classes, strict=True):
        assert c == 2
        assert 0 <= x1 < x2 <= 320
        assert 0 <= y1 < y2 <= 256
        inner = canvas[int(y1) + 2 : int(y2) - 2, int(x1) + 2 : int(x2) - 2].astype(int)
        assert inner.size == 0 or inner[..., 0].mean() > inner[..., 2].mean() + 60


def test_evaluation_counts_hits_misses_and_ignores_hidden_objects():
    gt = np.array([[0, 0, 10, 10], [20, 20, 30, 30], [40, 40, 50, 50]], float)
    gt_classes = np.array([0, 1, 0])
    visible = np.array([1.0, 1.0, 0.3])  # the third is too hidden to count
    evaluation = Evaluation(("a", "b"))
    preds = np.array([[0, 0, 10, 10], [40, 40, 50, 50], [70, 70, 80, 80]], float)
    evaluation.add(preds, np.array([0.9, 0.8, 0.7]), np.array([0, 0, 0]), gt, gt_classes, visible)
    report = evaluation.report()
    assert report["objects"] == 2
    assert report["recall"] == pytest.approx(0.5)  # found a, missed b
    assert report["precision"] == pytest.approx(0.5)  # one hit, one false box, one ignored
    perfect = Evaluation(("a", "b"))
    perfect.add(gt[:2], np.array([0.9, 0.9]), gt_classes[:2], gt, gt_classes, visible)
    assert perfect.report()["map50"] == pytest.approx(1.0)
    assert box_iou(gt, gt).diagonal() == pytest.approx(1.0)


def test_the_loss_learns_a_tiny_set():
    torch = pytest.importorskip("torch")
    from training.loss import detection_loss
    from training.model import Detector, anchor_points

    torch.manual_seed(0)
    model = Detector(len(CLASSES), width=8)
    images = torch.rand(2, 3, 64, 96)
    images[0, :, 16:40, 16:48] = 1.0
    gt_boxes = torch.tensor([[[16.0, 16.0, 48.0, 40.0]], [[0.0, 0.0, 0.0, 0.0]]])
    gt_classes = torch.tensor([[1], [-1]])
    points, strides = anchor_points(64, 96)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        raw = Detector.flatten(model(images))
        loss, _ = detection_loss(raw, points, strides, gt_boxes, gt_classes, gt_classes >= 0)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_export_writes_the_yolo_layout_with_class_names(tmp_path):
    torch = pytest.importorskip("torch")
    import onnx
    import onnxruntime as ort

    from training.export import export
    from training.model import Detector

    model = Detector(len(CLASSES), width=8)
    state = {
        "ema": model.state_dict(),
        "config": {"width": 8, "input": [96, 64], "classes": list(CLASSES)},
        "history": [],
    }
    torch.save(state, tmp_path / "ckpt.pt")
    sidecar = export(tmp_path / "ckpt.pt", tmp_path / "m.onnx")
    assert sidecar["classes"] == list(CLASSES)
    graph = onnx.load(str(tmp_path / "m.onnx"))
    names = ast.literal_eval({p.key: p.value for p in graph.metadata_props}["names"])
    assert names == dict(enumerate(CLASSES))
    session = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    batch = np.random.default_rng(0).random((3, 3, 64, 96), dtype=np.float32)
    out = session.run(None, {"images": batch})[0]
    anchors = (64 // 8) * (96 // 8) + (64 // 16) * (96 // 16) + (64 // 32) * (96 // 32)
    assert out.shape == (3, 4 + len(CLASSES), anchors)
    assert ((out[:, 4:] >= 0) & (out[:, 4:] <= 1)).all()


def test_training_leaves_subnormal_floats_as_it_found_them():
    """Flush-to-zero is process-wide: left on, later float code (and hypothesis) breaks."""
    pytest.importorskip("torch")
    from training.train import torch_cpu

    tiny = np.float64(1e-310)  # a subnormal
    with torch_cpu(1):
        pass
    assert tiny * np.float64(1.0) > 0
