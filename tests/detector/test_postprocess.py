"""Post-processing: decoding the YOLO output layout, per-class NMS, mapping into the image."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.detector.detect import DetectOptions, detections_from_output
from services.detector.letterbox import fit
from services.detector.postprocess import Candidates, box_iou, decode_output, nms


def output_of(rows: list[tuple[float, float, float, float, list[float]]]) -> np.ndarray:
    """A (4 + C, N) output from per-anchor (cx, cy, w, h, scores)."""
    return np.array([[cx, cy, w, h, *scores] for cx, cy, w, h, scores in rows], np.float32).T


def candidates(boxes, scores, class_ids) -> Candidates:
    return Candidates(
        np.asarray(boxes, dtype=np.float64).reshape(-1, 4),
        np.asarray(scores, dtype=np.float64),
        np.asarray(class_ids, dtype=np.int64),
    )


def test_decode_takes_each_anchors_best_class_and_converts_to_corners():
    out = output_of(
        [
            (100, 50, 20, 10, [0.1, 0.9]),
            (10, 10, 4, 4, [0.3, 0.2]),
            (60, 60, 8, 8, [0.05, 0.1]),  # under the threshold
        ]
    )
    got = decode_output(out, conf_threshold=0.25, max_candidates=100)
    assert got.boxes.tolist() == [[90, 45, 110, 55], [8, 8, 12, 12]]
    np.testing.assert_allclose(got.scores, [0.9, 0.3], rtol=1e-6)
    assert got.class_ids.tolist() == [1, 0]


def test_decode_threshold_is_inclusive_and_candidates_are_capped_best_first():
    out = output_of([(10, 10, 2, 2, [s]) for s in (0.5, 0.25, 0.75, 0.9)])
    assert len(decode_output(out, 0.25, 100)) == 4
    best = decode_output(out, 0.0, 2)
    np.testing.assert_allclose(best.scores, [0.9, 0.75], rtol=1e-6)


def test_decode_drops_non_finite_values_and_empty_boxes():
    out = output_of(
        [
            (10, 10, 2, 2, [float("nan")]),
            (float("inf"), 10, 2, 2, [0.9]),
            (10, 10, 0, 2, [0.9]),
            (10, 10, 2, -1, [0.9]),
            (10, 10, 2, 2, [0.8]),
        ]
    )
    got = decode_output(out, 0.1, 100)
    assert got.boxes.tolist() == [[9, 9, 11, 11]]


def test_decode_rejects_a_wrong_layout():
    with pytest.raises(ValueError, match="4 \\+ C"):
        decode_output(np.zeros((4, 10), np.float32), 0.1, 10)


def test_box_iou():
    ious = box_iou(np.array([0.0, 0.0, 10.0, 10.0]), np.array([[5.0, 0, 15, 10], [20, 20, 30, 30]]))
    np.testing.assert_allclose(ious, [50 / 150, 0.0])


def test_nms_suppresses_within_a_class_only():
    a = [0, 0, 10, 10]
    a_shifted = [1, 0, 11, 10]  # IoU 0.82 with a
    got = nms(candidates([a, a_shifted, a_shifted], [0.9, 0.8, 0.7], [0, 0, 1]), 0.5, 100)
    # the second class-0 box goes; the class-1 box at the same place survives
    assert got.boxes.tolist() == [a, a_shifted]
    assert got.class_ids.tolist() == [0, 1]


def test_nms_across_classes_drops_only_a_near_copy_of_another_classs_box():
    a = [0, 0, 10, 10]
    copy = [1, 0, 11, 10]  # IoU 0.82 with a: one object labelled twice
    behind = [2, 0, 12, 6]  # IoU 0.38: another object, partly hidden
    boxes, scores, classes = [a, copy, behind], [0.9, 0.8, 0.7], [0, 1, 2]
    got = nms(candidates(boxes, scores, classes), 0.5, 100, cross_class_iou=0.7)
    assert got.class_ids.tolist() == [0, 2]
    assert len(nms(candidates(boxes, scores, classes), 0.5, 100)) == 3  # off by default


def test_a_scene_model_is_served_with_suppression_across_classes():
    from services.detector.detect import SCENE_CROSS_CLASS_IOU
    from services.detector.settings import DetectorSettings

    settings = DetectorSettings()
    assert DetectOptions.from_settings(settings).cross_class_iou is None
    scene = DetectOptions.from_settings(settings, scene_model=True)
    assert scene.cross_class_iou == SCENE_CROSS_CLASS_IOU


def test_nms_keeps_boxes_at_exactly_the_threshold_and_caps_the_count():
    a, b = [0, 0, 10, 10], [5, 0, 15, 10]  # IoU 1/3
    assert len(nms(candidates([a, b], [0.9, 0.8], [0, 0]), 1 / 3, 100)) == 2
    assert len(nms(candidates([a, b], [0.9, 0.8], [0, 0]), 0.3, 100)) == 1
    far = [[20.0 * i, 0, 20.0 * i + 10, 10] for i in range(10)]
    assert len(nms(candidates(far, np.linspace(1, 0.1, 10), [0] * 10), 0.5, 3)) == 3


def test_nms_of_nothing_is_nothing():
    assert len(nms(candidates(np.zeros((0, 4)), [], []), 0.5, 10)) == 0


boxes_strategy = st.lists(
    st.tuples(
        st.floats(0, 90),
        st.floats(0, 90),
        st.floats(1, 30),
        st.floats(1, 30),
        st.floats(0.01, 1),
        st.integers(0, 2),
    ),
    max_size=40,
)


@given(rows=boxes_strategy, threshold=st.floats(0.1, 0.9))
@settings(max_examples=200, deadline=None)
def test_nms_properties(rows, threshold):
    """Kept boxes of one class never overlap by more than the threshold, and every dropped box
    overlaps a kept box of its class with at least its score by more than the threshold."""
    boxes = [[x, y, x + w, y + h] for x, y, w, h, _, _ in rows]
    scores = [s for *_, s, _ in rows]
    classes = [c for *_, c in rows]
    cands = candidates(boxes, scores, classes)
    kept = nms(cands, threshold, 1000)
    assert list(kept.scores) == sorted(kept.scores, reverse=True)
    for i in range(len(kept)):
        same = kept.class_ids == kept.class_ids[i]
        same[i] = False
        assert not np.any(box_iou(kept.boxes[i], kept.boxes[same]) > threshold)
    kept_rows = {tuple(b) + (c,) for b, c in zip(kept.boxes.tolist(), kept.class_ids, strict=True)}
    for box, score, cls in zip(cands.boxes, cands.scores, cands.class_ids, strict=True):
        if tuple(box.tolist()) + (cls,) in kept_rows:
            continue
        rivals = (kept.class_ids == cls) & (kept.scores >= score)
        assert np.any(box_iou(box, kept.boxes[rivals]) > threshold)


def test_detections_are_mapped_into_the_image_and_padding_boxes_dropped():
    box = fit((640, 360), (320, 320))  # scale 0.5, 70 rows of padding on top
    out = output_of(
        [
            (100, 120, 40, 60, [0.9, 0.0]),  # input (80, 90)-(120, 150)
            (100, 120, 40, 60, [0.0, 0.6]),  # same place, other class: kept
            (100, 30, 40, 40, [0.95, 0.0]),  # entirely in the top padding: dropped
            (10, 100, 40, 20, [0.0, 0.7]),  # crosses the left edge: clipped
        ]
    )
    got = detections_from_output(
        out, box, ["sphere", "cube"], None, DetectOptions(conf=0.5, colour=False)
    )
    assert [(d.label, d.box) for d in got] == [
        ("sphere", (160.0, 40.0, 240.0, 160.0)),
        ("cube", (0.0, 40.0, 60.0, 80.0)),
        ("cube", (160.0, 40.0, 240.0, 160.0)),
    ]
    assert [d.class_id for d in got] == [0, 1, 1]
    assert all(d.color is None for d in got)


def test_confidences_over_one_are_clamped():
    box = fit((320, 320), (320, 320))
    out = output_of([(50, 50, 10, 10, [1.5])])
    (only,) = detections_from_output(out, box, ["x"], None, DetectOptions(colour=False))
    assert only.confidence == 1.0
