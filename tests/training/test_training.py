"""The detector's training tools: dataset rendering, augmentation, metrics, loss and export."""

from __future__ import annotations

import ast
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.geometry.scene import SceneSpec
from services.detector.settings import DEFAULT_MODEL as GENERAL_MODEL
from training.data import LabelledImage, augment, load_dataset
from training.dataset import (
    CLASSES,
    TEXTURES,
    dataset_command,
    dataset_recipe,
    labelled_objects,
    random_scene,
    render_dataset,
    views,
)
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


def test_drone_views_leave_the_other_views_as_they_were(tmp_path):
    from services.common.geometry.free_camera import FreeCamera

    def key(v):
        return (v.scene.id, v.pose, v.width, v.spp, v.seed)

    plain = [key(v) for v in views(tmp_path, 5, 24)]
    mixed = [key(v) for v in views(tmp_path, 5, 24, drone_share=0.5)]
    drone = [m for m in mixed if isinstance(m[1], FreeCamera)]
    assert 0 < len(drone) < len(mixed)
    for p, m in zip(plain, mixed, strict=True):
        if not isinstance(m[1], FreeCamera):
            assert m == p
        else:
            assert (m[0], *m[2:]) == (p[0], *p[2:])  # the same scene, size, spp and seed
    assert all(isinstance(v.pose, FreeCamera) for v in views(tmp_path, 5, 8, drone_share=1.0))


def test_rendered_dataset_matches_the_renderer_ground_truth(tmp_path):
    assert render_dataset(tmp_path, count=4, seed=11) == 4
    assert render_dataset(tmp_path, count=4, seed=11) == 0  # resumes: nothing left to do
    recipe = dataset_recipe(tmp_path)
    assert recipe == {
        "count": 4,
        "seed": 11,
        "views_per_scene": 4,
        "builtin_share": 0.15,
        "drone_share": 0.0,
    }
    assert dataset_command("data/x", recipe).endswith(
        "--count 4 --seed 11 --views-per-scene 4 --builtin-share 0.15 --drone-share 0.0"
    )
    assert dataset_recipe(tmp_path / "elsewhere") is None
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


def test_a_drone_view_is_labelled_from_its_own_camera(tmp_path):
    from services.common.geometry.free_camera import FreeCamera
    from services.renderer.engine import RenderEngine
    from services.renderer.view import resolve_free_camera

    assert render_dataset(tmp_path, count=2, seed=11, drone_share=1.0) == 2
    view = next(iter(views(tmp_path / "check", 11, 1, drone_share=1.0)))
    meta = json.loads((tmp_path / "labels" / "000000.json").read_text())
    assert FreeCamera.model_validate(meta["pose"]) == view.pose
    engine = RenderEngine("auto", cache_size=1)
    engine.start()
    try:
        where = resolve_free_camera(view.scene, view.pose, view.width, view.height)
        ann = engine.annotate(view.scene, where, view.width, view.height, None)
    finally:
        engine.close()
    expected = sorted(o.box for o in labelled_objects(ann))
    assert sorted(tuple(o["box"]) for o in meta["objects"]) == expected


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


def test_fine_tuning_starts_from_the_shipped_model_and_says_so(tmp_path):
    pytest.importorskip("torch")
    from training.export import export
    from training.train import main as train_main

    shipped = json.loads(GENERAL_MODEL.with_suffix(".json").read_text())
    render_dataset(tmp_path / "data", count=4, seed=11, drone_share=0.5)
    run = tmp_path / "run"
    args = ["--data", str(tmp_path / "data"), "--val", str(tmp_path / "data"), "--run", str(run)]
    assert train_main([*args, "--epochs", "1", "--batch", "4", "--init", str(GENERAL_MODEL)]) == 0
    sidecar = export(run / "last.pt", tmp_path / "tuned.onnx")
    origin = sidecar["provenance"]["fine_tuned_from"]
    assert origin["sha256"] == shipped["sha256"]
    assert origin["provenance"]["train_images"] == shipped["provenance"]["train_images"]
    assert sidecar["parameters"] == shipped["parameters"]  # the shipped width, not --width's
    assert sidecar["provenance"]["val_dataset"] == str(tmp_path / "data")


def test_training_leaves_subnormal_floats_as_it_found_them():
    """Flush-to-zero is process-wide: left on, later float code (and hypothesis) breaks."""
    pytest.importorskip("torch")
    from training.train import torch_cpu

    tiny = np.float64(1e-310)  # a subnormal
    with torch_cpu(1):
        pass
    assert tiny * np.float64(1.0) > 0


@pytest.mark.parametrize("tuned", [False, True])
def test_the_general_card_names_the_base_model_of_a_fine_tune(tmp_path, tuned):
    from benchmarks.detector import table
    from training.card import write_general_card

    sidecar = json.loads(GENERAL_MODEL.with_suffix(".json").read_text())
    base = dict(sidecar["provenance"])
    if tuned:
        sidecar["provenance"] = {
            **base,
            "epochs": 12,
            "val_dataset": "data/drone/val",
            "dataset_recipes": {
                "data/drone/train": {
                    "count": 6000,
                    "seed": 11,
                    "views_per_scene": 4,
                    "builtin_share": 0.15,
                    "drone_share": 0.5,
                },
                "data/drone/old": None,
            },
            "fine_tuned_from": {
                "model": "detector.onnx",
                "sha256": "ab" * 32,
                "provenance": {**base, "epochs": 24},
            },
        }
    model = tmp_path / "detector.onnx"
    model.write_bytes(b"onnx")
    model.with_suffix(".json").write_text(json.dumps(sidecar))
    per = {"objects": 10, "precision": 0.9, "recall": 0.8, "ap50": 0.85, "map50": 0.85}
    report = {
        **per,
        "images": 3,
        "seed": 2,
        "scenes": ["demo"],
        "per_class": {"sphere": per},
        "by_view": {"drone": per},
        "centre_error_median_px": 0.8,
        "centre_error_p95_px": 3.0,
        "colour_error_median": None,
        "latency_images": 3,
        "latency_http_p50_ms": 15.0,
        "latency_in_process_p50_ms": 12.0,
    }
    write_general_card(tmp_path / "CARD.md", model, report, table(report))
    card = (tmp_path / "CARD.md").read_text()
    assert "(drone views)" in card
    assert ("| base model | `abababababababab…`" in card) is tuned
    assert ("--init models/detector.onnx" in card) is tuned
    assert ("--val data/drone/val --run data/runs/tuned" in card) is tuned
    rendered = (
        "training.dataset --out data/drone/train --count 6000 --seed 11 --views-per-scene 4 "
        "--builtin-share 0.15 --drone-share 0.5"
    )
    assert (rendered in card) is tuned
    assert "--out data/drone/old" not in card  # rendered before datasets kept their recipe
    assert "--val VAL" not in card
    assert "--epochs 24 --width 16" in card
