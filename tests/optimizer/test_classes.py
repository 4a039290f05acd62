"""Detector classes in matching: object classes pair only with themselves and give the proxy,
shape classes are a soft cost, and a second box of another class on one object is dropped."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.contracts.detect import Detection
from services.common.contracts.optimize import NextPoseRequest
from services.common.errors import UnprocessableError
from services.common.scene_models import ObjectClass
from services.optimizer.calibration import CalibrationStore
from services.optimizer.matching import COLOUR_GATE, compare_views
from services.optimizer.observations import (
    ALIKE_COST,
    CLASS_MISMATCH_COST,
    FORBIDDEN,
    Observation,
    appearance_cost,
    merge_duplicates,
)
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.proxies import ProxyKind

RED = (200.0, 30.0, 30.0)
BLUE = (30.0, 40.0, 200.0)
CAMERA = {"fov_deg": 45, "width": 320, "height": 240, "radius": 8.0}
GRID = {"angle_step_deg": 7.5, "min_theta_deg": 7.5, "max_theta_deg": 82.5}


def obs(labels, boxes, colors=None, confidence=None, classes=None) -> Observation:
    return Observation.from_arrays(labels, boxes, colors, confidence, classes)


def test_the_class_mismatch_cost_keeps_only_alike_colours_under_the_gate():
    assert CLASS_MISMATCH_COST + ALIKE_COST == COLOUR_GATE
    cost = appearance_cost(["sphere"], [RED], ["cone", "sphere"], [RED, RED])
    assert cost[0].tolist() == [CLASS_MISMATCH_COST, 0.0]
    assert appearance_cost(["a"], [RED], ["b"], [RED], FORBIDDEN)[0, 0] == FORBIDDEN
    # Unlike colours across classes stay over the gate.
    assert appearance_cost(["sphere"], [RED], ["cone"], [BLUE])[0, 0] >= COLOUR_GATE


def test_a_dark_object_s_noisy_colour_still_pairs_but_bright_unlike_colours_do_not():
    """Seen on a generated scene: one near-black cube's mean colour in two renders of the same
    pose (16 and 8 samples per pixel). Its chromaticities lie 0.18 apart, past the colour gate at
    the bright colours' scale, which left the true view unmatched and the search wandering."""
    target, view = (14.8, 0.5, 4.1), (65.6, 0.0, 35.4)
    assert appearance_cost(["cube"], [target], ["cube"], [view])[0, 0] < ALIKE_COST
    pair = compare_views(
        obs(["cube"], [[150.3, 96.4, 185.4, 131.8]], [target]),
        obs(["cube"], [[149.7, 96.4, 185.4, 131.6]], [view]),
    )
    assert len(pair.pairs) == 1
    # The same hues, bright, are as far apart as ever (and RED/BLUE stay apart when dark).
    bright = appearance_cost(["cube"], [(176.0, 6.0, 49.0)], ["cube"], [(150.0, 0.0, 81.0)])
    assert bright[0, 0] > 2.0
    dark_red, dark_blue = np.divide(RED, 4.0), np.divide(BLUE, 4.0)
    assert appearance_cost(["cube"], [dark_red], ["cube"], [dark_blue])[0, 0] >= COLOUR_GATE


def test_a_mislabelled_object_still_pairs_by_geometry_and_colour():
    """A dome called `sphere` in the target and `mesh` in the view is one object."""
    box = [100.0, 80.0, 140.0, 120.0]
    view = obs(["mesh"], [box], [RED])
    target = obs(["sphere"], [[101.0, 80.0, 141.0, 121.0]], [RED])
    comparison = compare_views(view, target)
    assert len(comparison.pairs) == 1
    assert comparison.rms_px < 1.0


def test_a_same_class_partner_wins_over_a_mislabelled_one():
    view = obs(["sphere"], [[100.0, 80.0, 140.0, 120.0]], [RED])
    target = obs(
        ["cube", "sphere"], [[100.0, 80.0, 140.0, 120.0], [104.0, 82.0, 144.0, 122.0]], [RED, RED]
    )
    comparison = compare_views(view, target)
    assert comparison.pairs.cols.tolist() == [1]


def test_identity_mode_pairs_only_equal_labels():
    classes = {"tower": ProxyKind.CONE, "bale1+bale2": ProxyKind.PRISM}
    box = [100.0, 80.0, 140.0, 120.0]
    view = obs(["tower"], [box], [RED], classes=classes)
    other = obs(["bale1+bale2"], [box], [RED], classes=classes)
    same = obs(["tower"], [[102.0, 80.0, 142.0, 120.0]], [RED], classes=classes)
    assert len(compare_views(view, other).pairs) == 0
    assert len(compare_views(view, same).pairs) == 1


def test_look_alike_members_of_one_class_pair_by_geometry():
    classes = {"bale1+bale2": ProxyKind.PRISM}
    boxes = [[40.0, 80.0, 80.0, 120.0], [200.0, 80.0, 240.0, 120.0]]
    view = obs(["bale1+bale2"] * 2, boxes, [RED, RED], classes=classes)
    target = obs(["bale1+bale2"] * 2, boxes[::-1], [RED, RED], classes=classes)
    comparison = compare_views(view, target)
    assert sorted(
        zip(comparison.pairs.rows.tolist(), comparison.pairs.cols.tolist(), strict=False)
    ) == [
        (0, 1),
        (1, 0),
    ]
    assert comparison.rms_px == 0.0


def test_identity_mode_takes_the_proxy_from_the_class_shape():
    classes = {"dome": ProxyKind.SPHERE, "tower": ProxyKind.CONE, "sphere": ProxyKind.PRISM}
    o = obs(["dome", "tower", "sphere"], np.zeros((3, 4)) + [0, 0, 1, 1], classes=classes)
    assert o.kinds.tolist() == [ProxyKind.SPHERE, ProxyKind.CONE, ProxyKind.PRISM]
    # Without classes the label names the shape.
    assert obs(["sphere"], [[0, 0, 1, 1]]).kinds.tolist() == [ProxyKind.SPHERE]


def detection(label, box, confidence=0.9, color=RED) -> Detection:
    return Detection(label=label, class_id=0, confidence=confidence, box=box, color=color)


@pytest.fixture(scope="module")
def context():
    return OptimizerContext(calibrations=CalibrationStore.load(), catalog=None)


def request(target, current, classes=None) -> NextPoseRequest:
    body = {
        "camera": CAMERA,
        "grid": GRID,
        "target": {"image_size": (320, 240), "detections": target},
        "history": [
            {"pose": {"lat": 3, "lon": 2}, "image_size": (320, 240), "detections": current}
        ],
    }
    if classes is not None:
        body["object_classes"] = classes
    return NextPoseRequest.model_validate(body)


def test_a_label_outside_the_object_classes_is_refused_naming_it(context):
    classes = [ObjectClass(label="tower", shape="cone", objects=("tower",))]
    body = request(
        [detection("tower", (100, 80, 140, 120))],
        [detection("tower", (100, 80, 140, 120)), detection("sphere", (10, 10, 30, 30))],
        classes,
    )
    with pytest.raises(UnprocessableError) as caught:
        next_pose(body, context)
    assert "history[0].detections[1].label" in str(caught.value.problem())


def test_object_class_labels_must_be_distinct():
    twice = [ObjectClass(label="a", shape="cone", objects=("a",))] * 2
    with pytest.raises(ValueError, match="distinct"):
        request([detection("a", (100, 80, 140, 120))], [], twice)


def test_a_second_box_of_another_class_on_one_object_is_dropped():
    o = obs(
        ["cylinder", "cone", "sphere"],
        [[100.0, 50.0, 140.0, 150.0], [102.0, 48.0, 141.0, 148.0], [200.0, 80.0, 240.0, 120.0]],
        confidence=[0.8, 0.45, 0.9],
    )
    kept, notes = merge_duplicates(o)
    assert kept.labels == ("cylinder", "sphere")
    assert len(notes) == 1
    assert notes[0].startswith("cone (0.45) taken as a second box on cylinder (0.80)")


def test_a_box_mostly_inside_a_similar_one_is_a_duplicate_but_a_small_one_is_not():
    # Half an L-shaped wall inside the whole wall's box: 100 % inside, 60 % of its area.
    wall = [[100.0, 50.0, 200.0, 100.0], [100.0, 50.0, 160.0, 100.0]]
    kept, _ = merge_duplicates(obs(["mesh", "cube"], wall, confidence=[0.7, 0.5]))
    assert kept.labels == ("mesh",)
    # A small object in front of a large one is another object.
    small = [[100.0, 50.0, 200.0, 100.0], [120.0, 60.0, 140.0, 80.0]]
    kept, notes = merge_duplicates(obs(["mesh", "sphere"], small, confidence=[0.7, 0.5]))
    assert kept.labels == ("mesh", "sphere")
    assert notes == ()
    # Same class: the detector's non-maximum suppression decides, not this rule.
    kept, _ = merge_duplicates(obs(["cube", "cube"], wall, confidence=[0.7, 0.5]))
    assert len(kept) == 2


def test_the_answer_says_which_boxes_were_merged(context):
    target = [detection("sphere", (100, 80, 140, 120)), detection("cube", (200, 80, 240, 120))]
    current = [
        detection("cylinder", (100, 80, 140, 120), 0.8),
        detection("cone", (101, 80, 140, 121), 0.4),
        detection("cube", (200, 80, 240, 120)),
    ]
    answer = next_pose(request(target, current), context)
    assert "current view: cone (0.40) taken as a second box on cylinder (0.80)" in answer.reason
    assert answer.match is not None
    assert answer.match.pairs == 2
    # In identity mode overlapping classes are distinct objects: nothing is merged.
    classes = [
        ObjectClass(label=name, shape="cube", objects=(name,))
        for name in ("sphere", "cube", "cylinder", "cone")
    ]
    answer = next_pose(request(target, current, classes), context)
    assert "second box" not in answer.reason
