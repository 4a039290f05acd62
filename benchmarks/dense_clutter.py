"""Dense fits on edge-rich targets: shares taken raw against shares above the target's chance.

Run: ``.venv/bin/python -m benchmarks.dense_clutter [--cases DIR] [--n 8] [--seeds 1,5]``

Cases: the ``clean`` cases of :mod:`benchmarks.dense_light` (same ``--cases`` folder, captured
there if missing): free targets of the demo scene and of two generated scenes per seed, each
with one render at the box solver's answer. Each target is put half under a blocky noise
texture of strength ``s`` (0, 0.25, 0.5: the grey is ``(1 − s) g + s · 255 · noise``, 3-pixel
blocks, seeded per case): edges everywhere, as gravel or foliage would give. It is refined
(:func:`~services.optimizer.free.dense.refine_dense`, as ``/refine-pose`` does) from its own
render (*right*: the box pose) and from the render of the scene's next target (*wrong*:
another camera on the same film).

Per strength and kind it prints the target's median edge chance
(:attr:`~services.optimizer.free.dense.DenseFit.chance`); how many fits would converge
(``refine_pose.converges``) with the shares taken raw and above chance; how many leave the
share at which a render agrees by its edges (the controller's ``EDGE_SHARE``), raw and above
chance; and, for the right renders, how many fits end within 5 % of the radius and 2°.
"""

from __future__ import annotations

import statistics
from collections import defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from benchmarks.dense_light import captured_cases
from benchmarks.dense_refine import load_pair
from cosmos.bench.free_targets.metrics import rotation_angle_deg
from services.controller.free_refine import EDGE_SHARE
from services.optimizer.free.dense import DenseFit, refine_dense
from services.optimizer.refine_pose import converges

STRENGTHS: Final = (0.0, 0.25, 0.5)
BLOCK_PX: Final = 3


def textured(gray: np.ndarray, strength: float, seed: int) -> np.ndarray:
    """``gray`` under a blocky noise texture of ``strength`` (module docstring)."""
    if strength == 0.0:
        return gray
    height, width = gray.shape
    blocks = np.random.default_rng(seed).random((height // BLOCK_PX + 1, width // BLOCK_PX + 1))
    noise = cv2.resize(blocks, (width, height), interpolation=cv2.INTER_NEAREST)
    noise = cv2.GaussianBlur(noise, (0, 0), 0.8)
    mixed = (1.0 - strength) * gray.astype(np.float64) + strength * 255.0 * noise
    return np.asarray(np.clip(mixed, 0, 255), dtype=np.uint8)


def _scene_groups(folder: Path) -> dict[str, list[Path]]:
    """The clean cases by scene and seed, in target order."""
    groups: dict[str, list[Path]] = defaultdict(list)
    for path in sorted(folder.glob("*-clean.npz")):
        groups[path.name.rsplit("-", 2)[0]].append(path)
    return groups


def _tally(row: list[int], fit: DenseFit, right: dict[str, Any] | None) -> None:
    """Count one fit into ``row``: n, converged raw / above chance, agreeing raw / above chance,
    and (a right render) within 5 %/2°."""
    row[0] += 1
    raw = replace(fit, chance=0.0)
    row[1] += converges(raw)
    row[2] += converges(fit)
    row[3] += raw.share() >= EDGE_SHARE
    row[4] += fit.share() >= EDGE_SHARE
    if right is not None:
        truth = right["truth"]
        moved = float(np.linalg.norm(fit.position - np.asarray(truth.position))) / right["radius"]
        turned = rotation_angle_deg(fit.rotation, np.asarray(truth.rotation))
        row[5] += moved <= 0.05 and turned <= 2.0


def _fit(target: np.ndarray, render: dict[str, Any]) -> DenseFit:
    return refine_dense(
        target,
        render["rgb"],
        render["depth"],
        render["camera"],
        fit_focal=bool(render["fit_focal"]),
        near=render["near"],
    )


def main() -> None:
    folder = captured_cases(__doc__.splitlines()[0])
    rows: dict[tuple[float, str], list[int]] = defaultdict(lambda: [0] * 6)
    chances: dict[float, list[float]] = defaultdict(list)
    for group in _scene_groups(folder).values():
        cases = [load_pair(path) for path in group]
        for i, case in enumerate(cases):
            other = cases[(i + 1) % len(cases)]
            for strength in STRENGTHS:
                target = textured(case["target"], strength, seed=i)
                fit = _fit(target, case)
                chances[strength].append(fit.chance)
                _tally(rows[strength, "right"], fit, case)
                if other is not case and other["target"].shape == target.shape:
                    _tally(rows[strength, "wrong"], _fit(target, other), None)
    print(
        "texture  render   n  chance  converged raw · above chance  "
        f"≥ {EDGE_SHARE:.0%} raw · above chance  within 5 %/2°"
    )
    for (strength, kind), (n, raw, above, agree, agree_above, inside) in sorted(rows.items()):
        within = f"{inside}/{n}" if kind == "right" else "—"
        print(
            f"{strength:7.2f}  {kind:6s} {n:3d}  {statistics.median(chances[strength]):6.2f}  "
            f"{raw:>12d} · {above:<14d}  {agree:>9d} · {agree_above:<12d}  {within}"
        )


if __name__ == "__main__":
    main()
