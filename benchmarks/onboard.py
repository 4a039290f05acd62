"""Onboarding a scene: prints minutes per stage and its own detector's held-out precision, recall.

Run ``python -m benchmarks.onboard`` (the garden scene, copied to a temporary folder so that the
shipped ``scenes/garden.detector/`` stays as it is) or ``python -m benchmarks.onboard --scene
PATH`` (onboards that scene in place). Goals: the whole run within 10 minutes on 2 CPU cores,
precision and recall at least 0.98 on the scene's held-out renders.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

from services.common.catalog import BUILTIN_SCENES_DIR

__all__ = ["main"]

GOAL_MINUTES = 10.0
GOAL_PR = 0.98


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="a scene file (default: a copy of garden)")
    parser.add_argument("--work", type=Path, help="work folder (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    from training.onboard import OnboardOptions, onboard_scene

    with tempfile.TemporaryDirectory(prefix="cosmos-onboard-") as tmp:
        scene = args.scene
        if scene is None:
            for part in ("garden.yaml", "meshes", "textures"):
                source = BUILTIN_SCENES_DIR / part
                if source.is_dir():
                    shutil.copytree(source, Path(tmp) / part)
                else:
                    shutil.copy(source, Path(tmp) / part)
            scene = Path(tmp) / "garden.yaml"
        work = args.work if args.work is not None else Path(tmp) / "work"
        options = OnboardOptions(seed=args.seed)
        report = onboard_scene(scene, options, work_dir=work)
    m = report.minutes
    print(f"scene {report.scene}: {len(report.classes)} classes ({', '.join(report.classes)})")
    print(f"images {report.images} train + {report.val_images} held-out, {report.epochs} epochs")
    print(
        f"minutes: render {m.render:.2f}, train {m.train:.2f}, evaluate+export {m.eval:.2f}, "
        f"total {m.total:.2f}"
    )
    print(f"{'class':<16} {'objects':>7} {'precision':>9} {'recall':>7} {'AP50':>6}")
    for label, row in report.per_class.items():
        print(
            f"{label:<16} {int(row['objects']):>7} {row['precision']:>9.3f} "
            f"{row['recall']:>7.3f} {row['ap50']:>6.3f}"
        )
    print(
        f"{'overall':<16} {'':>7} {report.precision:>9.3f} {report.recall:>7.3f} "
        f"{report.map50:>6.3f} (mAP50)"
    )
    time_ok = m.total <= GOAL_MINUTES
    pr_ok = report.precision >= GOAL_PR and report.recall >= GOAL_PR
    print(
        f"goals: total <= {GOAL_MINUTES:.0f} min {'met' if time_ok else 'NOT met'}; "
        f"precision and recall >= {GOAL_PR} {'met' if pr_ok else 'NOT met'}"
    )
    return 0 if time_ok and pr_ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
