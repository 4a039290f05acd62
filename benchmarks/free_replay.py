"""The box solve replayed offline on the detections a free bench run recorded: how often the
estimate from the target's boxes alone lands within 10 %/5° (and 5 %/2°), as recorded by the
run (the pose it rendered first) and as this code solves the same detections now.

Run: ``.venv/bin/python -m benchmarks.free_replay out/bench-free/free.json [more.json …]
[--variant clean --variant jpeg …] [--all-variants] [--dump replay.jsonl] [--attitude σ]``
(``--dump``: each record's replayed error and status, to compare two versions of the code record
by record; ``--attitude``: each solve is also given the true camera's pitch and roll, each off by
a seeded normal draw of σ degrees, as a drone's gimbal states them in its photo's XMP)

Each report is one ``cosmos bench --free`` run whose records kept their target detections
(``FreeRecord.target_detections``). Its generated scenes are made again from the run's seed, as
the run made them (:func:`cosmos.bench.scenes.generate_scene`); each record's detections go to
:func:`services.optimizer.free_pose.free_pose`, the optimizer's own domain function, with the
target's fov when the search was given it and the shipped detector's input size. It prints, per
detector (``own``: a scene's own model; ``general``: the shape model on generated scenes), per
elevation band and per given or not given fov, the shares within the two tolerances and the
replayed statuses. By default only the goal's variants (clean, JPEG, noise) are counted.

It runs in seconds, where the bench takes minutes: a change to the box solve is measured here
first, then through the stack.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import zlib
from collections import Counter, defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from cosmos.bench.free_bench.records import FreeRecord
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import PoseError, pose_error
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.contracts.free import CameraAttitude, FreePoseRequest, PhotoIntrinsics
from services.common.contracts.optimize import ImageDetections
from services.common.geometry.free_camera import (
    rotation_of_quaternion,
    yaw_pitch_roll_of_rotation,
)
from services.optimizer.free_pose import SceneObjectCache, free_pose
from services.renderer.settings import RendererSettings

GOAL_VARIANTS: Final = ("clean", "jpeg", "noise")
DETECTOR_INPUT: Final = (320, 256)
"""The shipped detector's network input (``model.input_size``), as the controller passes it."""
LIMITS: Final = ((0.10, 5.0), (0.05, 2.0))


def stated_attitude(record: FreeRecord, sigma_deg: float) -> CameraAttitude:
    """The true camera's pitch and roll, each off by a normal draw of ``sigma_deg`` seeded by the
    record's place in its run (a gimbal's error)."""
    key = f"{record.scene}/{record.variant}/{record.index}/{record.detector}".encode()
    off = np.random.default_rng(zlib.crc32(key)).normal(0.0, sigma_deg, size=2)
    _, pitch, roll = yaw_pitch_roll_of_rotation(
        rotation_of_quaternion(record.truth.quaternion_wxyz)
    )
    return CameraAttitude(
        pitch_deg=float(np.clip(pitch + off[0], -90.0, 90.0)),
        roll_deg=float((roll + off[1] + 180.0) % 360.0 - 180.0),
    )


def replayed(
    record: FreeRecord,
    catalog: SceneCatalog,
    cache: SceneObjectCache,
    attitude_sigma: float | None = None,
) -> tuple[PoseError, str]:
    """The box solve's error and status on ``record``'s detections, solved now (given the
    camera's attitude off by ``attitude_sigma`` degrees, when not None)."""
    assert record.target_size is not None
    intrinsics = PhotoIntrinsics(fov_deg=record.truth.fov_deg) if record.intrinsics_given else None
    request = FreePoseRequest(
        scene=record.scene,
        target=ImageDetections(image_size=record.target_size, detections=record.target_detections),
        intrinsics=intrinsics,
        detector_input=DETECTOR_INPUT,
        attitude=None if attitude_sigma is None else stated_attitude(record, attitude_sigma),
    )
    answer = free_pose(request, catalog, cache)
    pose = answer.pose
    estimate = None
    if pose is not None:
        estimate = Estimate.of_camera(pose.camera(), pose.intrinsics.fov_deg, record.target_size[0])
    return pose_error(estimate, record.truth.estimate(), record.radius), answer.status


def run_catalog(config: dict[str, Any], folder: Path, settings: RendererSettings) -> SceneCatalog:
    """The scenes a run searched: the built-in ones and its generated ones, made again from its
    seed into ``folder`` (:func:`cosmos.bench.scenes.generate_scene`, as the run made them)."""
    seed = int(config["seed"])
    for i in range(int(config.get("random_scenes") or 0)):
        generate_scene(np.random.default_rng([seed, i]), folder, f"rand{seed}-{i}")
    return SceneCatalog([*settings.scene_directories(), folder])


def _records(path: Path, variants: Sequence[str] | None) -> tuple[list[FreeRecord], dict[str, Any]]:
    report = json.loads(path.read_text())
    records = [FreeRecord.model_validate(r) for r in report["records"]]
    kept = [
        r
        for r in records
        if r.target_size is not None and (variants is None or r.variant in variants)
    ]
    return kept, report["config"]


def _cell(hits: Sequence[bool]) -> str:
    return f"{sum(hits)}/{len(hits)}" if hits else "-"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.free_replay", description=__doc__)
    parser.add_argument("reports", nargs="+", type=Path, help="free.json of cosmos bench --free")
    parser.add_argument("--variant", action="append", help="count only these (repeatable)")
    parser.add_argument("--all-variants", action="store_true")
    parser.add_argument(
        "--dump", type=Path, help="write each record's replayed error and status here (JSON lines)"
    )
    parser.add_argument(
        "--attitude",
        type=float,
        metavar="SIGMA",
        help="give each solve the true pitch and roll, off by a normal draw of SIGMA degrees",
    )
    args = parser.parse_args(argv)
    dumped: list[str] = []
    variants = None if args.all_variants else (args.variant or list(GOAL_VARIANTS))
    rows: dict[tuple[str, str, str], list[tuple[bool, ...]]] = defaultdict(list)
    statuses: Counter[str] = Counter()
    settings = RendererSettings()
    for path in args.reports:
        records, config = _records(path, variants)
        if not records:
            sys.stderr.write(f"{path}: no records with target detections (an older run?)\n")
            continue
        with tempfile.TemporaryDirectory(prefix="cosmos-replay-") as tmp:
            catalog = run_catalog(config, Path(tmp), settings)
            cache = SceneObjectCache()
            for record in records:
                error, status = replayed(record, catalog, cache, args.attitude)
                statuses[status] += 1
                where = [str(path), record.detector, record.scene, record.variant]
                ident = [*where, record.index, record.given]
                errors = [error.position, error.rotation_deg]
                dumped.append(json.dumps({"key": ident, "error": errors, "status": status}))
                was = record.error("boxes")
                hits = (
                    *(was.within(*lim) for lim in LIMITS),
                    *(error.within(*lim) for lim in LIMITS),
                )
                for band in (record.band, "all"):
                    rows[(record.detector, band, record.given)].append(hits)
                    rows[(record.detector, band, "all")].append(hits)
    print("boxes within 10 %/5° · 5 %/2°: as recorded → replayed with this code")
    print(f"{'detector':8s} {'band':6s} {'fov':13s} {'recorded':>17s} {'replayed':>17s}")
    for key in sorted(rows):
        row = rows[key]
        recorded = " · ".join(_cell([h[k] for h in row]) for k in (0, 1))
        now = " · ".join(_cell([h[k] for h in row]) for k in (2, 3))
        print(f"{key[0]:8s} {key[1]:6s} {key[2]:13s} {recorded:>17s} {now:>17s}")
    print("replayed statuses: " + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
    if args.dump:
        args.dump.write_text("".join(line + "\n" for line in dumped))
    return 0


if __name__ == "__main__":
    sys.exit(main())
