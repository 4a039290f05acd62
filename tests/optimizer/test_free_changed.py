"""A scene that changed since it was modelled (one object moved, the ``changed`` variant):
the pose is the one the unmoved objects agree on, not one that pairs every box loosely, and a
wrong pose is never called found."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera
from services.optimizer.free import SceneObjects, scene_objects, solve_free_pose
from tests.optimizer.test_free_pose import H, W, errors, exact_detections, intrinsics_of

MOVED_BALL_VIEWS = Path(__file__).parent / "data" / "moved_ball_views.json"
VIEWS = [
    FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0)),
    FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0),
    FreeCamera(position=(0.3, 0.2, 9.0), yaw_deg=30.0, pitch_deg=90.0),
    FreeCamera(position=(2.0, 7.0, 3.5), look_at=(-0.5, 0.5, 0.0), roll_deg=-10.0),
]


def moved_one(objects: SceneObjects, index: int, shift: np.ndarray) -> SceneObjects:
    """``objects`` with object ``index`` moved by ``shift``."""
    points = objects.points.copy()
    points[objects.owners() == index] += shift
    centroids = objects.centroids.copy()
    centroids[index] += shift
    return dataclasses.replace(objects, points=points, centroids=centroids)


def test_a_moved_object_does_not_pull_the_pose_away(catalog):
    """Every object of demo and garden moved in turn (up to 2 units) under four views: 44
    targets. Ranked by pairs first, 4 answers were wrong and 3 of them found (20-125° off)."""
    wrong, found_wrong, targets = [], [], 0
    for sid in ("demo", "garden"):
        objects = scene_objects(catalog.get(sid).spec, catalog.get(sid).assets)
        for view, camera in enumerate(VIEWS):
            pinhole = free_pinhole_camera(camera, W, H, objects.fov_deg)
            rng = np.random.default_rng(view)
            for index in range(len(objects)):
                changed = moved_one(objects, index, np.r_[rng.uniform(-2.0, 2.0, 2), 0.0])
                detections = exact_detections(changed, pinhole, 0.5, rng)
                if len(detections) < 5:
                    continue
                targets += 1
                answer = solve_free_pose(objects, detections, W, H, intrinsics_of(pinhole))
                moved, turned = errors(answer.pose, pinhole)
                if moved > 0.05 * objects.radius or turned > 2.0:
                    wrong.append((sid, view, index))
                    if answer.status == "found":
                        found_wrong.append((sid, view, index, answer.reason))
    assert targets >= 40
    assert found_wrong == []
    assert len(wrong) <= 2, wrong  # the nadir view of demo's five equal balls stays ambiguous


def demo_view(catalog, boxes: dict[str, list[float]], truth: FreeCamera):
    """The box solve of demo detections ``boxes`` (label → box); its answer's position and
    rotation errors against ``truth``, and the objects it paired."""
    detections = [
        Detection(label=label, class_id=i, confidence=0.9, box=tuple(box))
        for i, (label, box) in enumerate(boxes.items())
    ]
    objects = scene_objects(catalog.get("demo").spec, catalog.get("demo").assets)
    pinhole = free_pinhole_camera(truth, W, H, objects.fov_deg)
    answer = solve_free_pose(objects, detections, W, H, intrinsics_of(pinhole))
    assert answer.pose is not None
    moved, turned = errors(answer.pose, pinhole)
    paired = {c.object for c in answer.pose.correspondences}
    return moved / objects.radius, turned, paired


def assert_the_unmoved_pin(catalog, view: str) -> None:
    """The box solve of a recorded demo view (``data/moved_ball_views.json``: the detector's
    boxes, the true camera) pairs its unmoved balls and lands within its bounds (share of the
    radius, degrees) of the truth."""
    case = json.loads(MOVED_BALL_VIEWS.read_text())[view]
    truth = FreeCamera.model_validate(case["truth"])
    moved, turned, paired = demo_view(catalog, case["boxes"], truth)
    assert moved < case["within"][0]
    assert turned < case["within"][1]
    assert paired == set(case["unmoved"])


def test_a_fit_that_pairs_a_moved_box_is_refitted_without_each_loose_pair(catalog):
    """The detector's boxes of a demo view whose magenta ball had moved 0.96 units (``cosmos
    bench --free --scene demo --random-scenes 2 --n 8 --seed 3``, target 0, ``changed``). Every
    hypothesis that pairs all five boxes fits them at 6.3 px, the red ball's pair the loosest
    (9.2 px) and the moved one's next (9.0 px); the minimal sets without the magenta ball all
    landed in the far basin of a flip. The pose was answered 18 % of the radius and 7° off;
    refitted without each loose pair, the four unmoved balls give the true pose."""
    assert_the_unmoved_pin(catalog, "seed3_target0_magenta")


def test_boxes_the_border_cuts_keep_a_moved_box_from_being_fitted_exactly(catalog):
    """The detector's boxes of a demo view whose yellow ball had moved 0.55 units (``cosmos
    bench --free --scene demo,garden --random-scenes 3 --n 8 --onboard none --seed 27``, target
    7, ``changed``). The border cuts the green and blue balls. When the centre PnP left cut boxes
    out, three centres were left, the moved one among them, and three points are fitted exactly:
    every hypothesis, the best 2 % of the radius off, went 1.3 radii away, and the answer paired
    two balls. With the cut boxes kept until four uncut ones remain, refitted without the moved
    ball, the four others give the true pose."""
    assert_the_unmoved_pin(catalog, "seed27_target7_yellow")


def test_hypotheses_that_all_pair_a_moved_box_give_way_to_the_next(catalog):
    """The detector's boxes of a demo view from 10-30° through a wide lens (``cosmos bench
    --free --scene demo --scene garden --n 6 --seed 43 --target-width 1280 --roll-limit 90
    --fov-range 1.5,2.2``, target 5, ``changed``: the red ball moved 0.97 units; its boxes here
    a quarter of the photo's, as the solve takes them in the detector's pixels). The six best
    hypotheses all paired the moved ball, for pairing five boxes; their fits went to the far
    basin of a flip, where the pairs re-drawn came down to two, and the answer was 162 % of the
    radius off. The next hypothesis pairs the four other balls: the true pose."""
    assert_the_unmoved_pin(catalog, "seed43_target5_red")
