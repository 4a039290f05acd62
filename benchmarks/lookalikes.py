"""Many look-alike objects: the pose from boxes alone when a scene's own detector names one class
for all of them (a car park, a row of containers), so each box may be any of them.

Run: ``.venv/bin/python -m benchmarks.lookalikes [--counts 8,12,20] [--n 20] [--noise 0.7]
[--seed 1] [--unique]``

Per count, ``--n`` trials, each a layout of that many identical cubes drawn at random on the
ground (``--unique`` adds a tower and a ball of their own classes) and a drone camera drawn at
random (distance 5-10, elevation 50-89°, looking near the centre, roll within ±20°, fov 60°,
640 × 480). The boxes are the cubes' exact projected boxes with Gaussian noise of ``--noise``
pixels on every edge, those at least 60 % inside the film; the focal length is known. It
prints, per count, how many answers were ``found`` within 5 % of the radius of the truth
(right) or farther (wrong), how many ``ambiguous`` ones hold the truth as their pose or among
their alternatives, or not at all, and the median solve time.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections import Counter
from pathlib import Path

import numpy as np

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera, orbit_position
from services.common.geometry.scene import parse_scene
from services.optimizer.free import (
    FreePoseAnswer,
    Intrinsics,
    PoseCandidate,
    SceneObjects,
    project_boxes,
    scene_objects,
    solve_free_pose,
)

W, H, FOV, RADIUS = 640, 480, 60.0, 10.0


def layout(count: int, rng: np.random.Generator, unique: bool) -> SceneObjects:
    """``count`` identical cubes at random on the ground (and a tower and a ball)."""
    lines = [
        f"  - {{name: cube{i}, shape: cube, position: [{x:.3f}, {y:.3f}], size: 0.5, "
        "color: [0.2, 0.3, 0.8]}"
        for i, (x, y) in enumerate(rng.uniform(-4.0, 4.0, (count, 2)))
    ]
    if unique:
        lines.append(
            "  - {name: tower, shape: cylinder, position: [0.5, 0.3], radius: 0.4, height: 2.0, "
            "color: [0.9, 0.1, 0.1]}"
        )
        lines.append(
            "  - {name: ball, shape: sphere, position: [-2.0, 2.5], radius: 0.5, "
            "color: [0.1, 0.9, 0.1]}"
        )
    text = (
        f"camera: {{fov_deg: {FOV}, width: {W}, height: {H}, radius: {RADIUS}}}\n"
        "lighting: {point: {position: [3.0, 3.0, 12.0], intensity: 300.0}}\n"
        "ground: {size: 14.0, color: [0.5, 0.5, 0.5]}\n"
        "objects:\n" + "\n".join(lines) + "\n"
    )
    return scene_objects(parse_scene(text, Path("lookalikes.yaml")))


def drone(rng: np.random.Generator) -> FreeCamera:
    distance = rng.uniform(5.0, 10.0)
    elevation = float(rng.uniform(50.0, 89.0))
    azimuth = math.degrees(rng.uniform(0.0, 2.0 * math.pi))
    position = orbit_position((0.0, 0.0, 0.0), distance, elevation, azimuth)
    look = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), 0.0)
    return FreeCamera(
        position=position, look_at=look, roll_deg=rng.uniform(-20.0, 20.0), fov_deg=FOV
    )


def trial(
    objects: SceneObjects, camera: FreeCamera, noise: float, rng: np.random.Generator
) -> tuple[str, float]:
    """One view solved: its outcome (module docstring) and the solve's seconds."""
    pinhole = free_pinhole_camera(camera, W, H, FOV)
    boxes = project_boxes(
        objects,
        np.asarray(pinhole.rotation),
        np.asarray(pinhole.translation),
        (pinhole.fx, pinhole.fy),
        (pinhole.cx, pinhole.cy),
    )
    detections = []
    for i, box in enumerate(boxes):
        noisy = box + rng.normal(0.0, noise, 4)
        clipped = np.clip(noisy, 0.0, [W, H, W, H])
        area = (clipped[2] - clipped[0]) * (clipped[3] - clipped[1])
        if min(clipped[2] - clipped[0], clipped[3] - clipped[1]) > 3.0 and area > 0.6 * (
            (noisy[2] - noisy[0]) * (noisy[3] - noisy[1])
        ):
            box_xyxy = (float(clipped[0]), float(clipped[1]), float(clipped[2]), float(clipped[3]))
            detections.append(
                Detection(label=objects.labels[i], class_id=0, confidence=0.9, box=box_xyxy)
            )
    k = Intrinsics(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy)
    started = time.perf_counter()
    answer = solve_free_pose(objects, detections, W, H, k)
    return outcome(answer, np.asarray(pinhole.position)), time.perf_counter() - started


def outcome(answer: FreePoseAnswer, truth: np.ndarray) -> str:
    def right(pose: PoseCandidate) -> bool:
        return float(np.linalg.norm(np.asarray(pose.position) - truth)) < 0.05 * RADIUS

    if answer.pose is None:
        return "failed"
    if answer.status == "found":
        return "found right" if right(answer.pose) else "found WRONG"
    if right(answer.pose):
        return "ambiguous, truth best"
    if any(right(p) for p in answer.alternatives):
        return "ambiguous, truth among"
    return "ambiguous, truth missing"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--counts", default="8,12,20")
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--noise", type=float, default=0.7)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--unique", action="store_true")
    args = parser.parse_args(argv)
    for count in (int(c) for c in args.counts.split(",")):
        rng = np.random.default_rng([args.seed, count])
        outcomes: Counter[str] = Counter()
        seconds = []
        for _ in range(args.n):
            said, took = trial(layout(count, rng, args.unique), drone(rng), args.noise, rng)
            outcomes[said] += 1
            seconds.append(took)
        shown = ", ".join(f"{name} {number}" for name, number in sorted(outcomes.items()))
        print(
            f"{count} look-alikes, {args.n} views: {shown}; "
            f"median solve {1000 * statistics.median(seconds):.0f} ms"
        )


if __name__ == "__main__":
    main()
