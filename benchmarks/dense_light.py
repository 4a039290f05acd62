"""Dense fit under another light: all the render's edges against its outline only, per band.

Run: ``.venv/bin/python -m benchmarks.dense_light [--cases DIR] [--n 8] [--seeds 1,5]``

Cases: free targets (``cosmos.bench.free_targets``' draw) of the demo scene and of two generated
scenes per seed, each solved from its exact boxes with the detector's edge noise (the box
solver's answer), rendered once at that answer (colours, depth, object ids and outline shading,
8 samples a pixel, as a search's view) and paired with the target's ``clean``, ``jpeg`` and
``photo`` images (``photo``: the scene under a light turned and tilted away, finished as a
camera would; :mod:`cosmos.bench.free_bench.targets`). They are drawn and rendered once (in
this process), one ``.npz`` each in ``--cases``, so an interrupted capture resumes.

Each case is refined twice with :func:`~services.optimizer.free.dense.refine_dense`: on all the
render's edges, and on those near its outline (:func:`~services.optimizer.free.edges.outline`),
the others joining a last fit when the target shows them (what ``/refine-pose`` does). It
prints, per image variant and elevation band, the shares within 5 % of the radius and 2° and
within 2 % and 1°, and how many cases the outline put inside 5 %/2° that all edges left out,
and the reverse.
"""

from __future__ import annotations

import argparse
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any, Final

import numpy as np

from benchmarks.dense_refine import load_pair, save_pair
from cosmos.bench.free_bench.targets import variant_image
from cosmos.bench.free_targets.dense import render_at
from cosmos.bench.free_targets.draw import DrawError, FreeTarget, draw_targets
from cosmos.bench.free_targets.metrics import rotation_angle_deg
from cosmos.bench.free_targets.rendering import LocalRenderer
from cosmos.bench.free_targets.shapes import scene_shapes
from cosmos.bench.free_targets.solver import solve_target
from cosmos.bench.runner import TARGET_SPP
from cosmos.bench.scenes import generate_scene
from services.common.catalog import SceneCatalog
from services.common.geometry.camera import PinholeCamera
from services.common.geometry.scene import LoadedScene
from services.optimizer.free import SceneObjects, scene_objects
from services.optimizer.free.dense import refine_dense
from services.renderer.settings import RendererSettings

VARIANTS: Final = ("clean", "jpeg", "photo")
VIEW_SPP: Final = 8
"""Samples a pixel of the render at the answer: the controller's default for a search's view."""
METHODS: Final = ("all edges", "outline")


def _name(scene_id: str, seed: int, index: int, variant: str) -> str:
    return f"{scene_id}-s{seed}-{index:02d}-{variant}.npz"


def capture(folder: Path, n: int, seeds: list[int]) -> None:
    """Draw, solve, render and degrade the cases into ``folder`` (module docstring); cases
    already there are kept."""
    folder.mkdir(parents=True, exist_ok=True)
    settings = RendererSettings()
    with tempfile.TemporaryDirectory(prefix="cosmos-dense-light-") as tmp:
        scenes = [("demo", seeds[0])]
        for seed in seeds:
            for i in range(2):
                generate_scene(np.random.default_rng([seed, i]), Path(tmp), f"rand{seed}-{i}")
                scenes.append((f"rand{seed}-{i}", seed))
        catalog = SceneCatalog([*settings.scene_directories(), Path(tmp)])
        with LocalRenderer(catalog, settings) as renderer:
            for scene_id, seed in scenes:
                done = folder / f"{scene_id}-s{seed}.done"
                if done.exists():
                    continue
                scene = catalog.get(scene_id)
                objects = scene_objects(scene.spec, scene.assets)
                try:
                    targets = draw_targets(renderer, scene, scene_shapes(scene), n, seed)
                except DrawError as exc:
                    print(f"skipped {scene_id}: {exc}")
                    continue
                for target in targets:
                    _capture_target(folder, renderer, scene, objects, target, seed, Path(tmp))
                done.touch()
                print(f"{scene_id} (seed {seed}): {len(targets)} targets captured")


def _capture_target(
    folder: Path,
    renderer: LocalRenderer,
    scene: LoadedScene,
    objects: SceneObjects,
    target: FreeTarget,
    seed: int,
    altered: Path,
) -> None:
    """One target's cases: the box solver's answer rendered once, with each variant's image."""
    answer = solve_target(target, objects, np.random.default_rng([seed, target.index, 2]))
    if answer.pose is None:
        return
    rendered = render_at(renderer, target, answer.pose.free_camera(), VIEW_SPP)
    if rendered is None:
        return
    for variant in VARIANTS:
        image = variant_image(
            renderer, scene, target, variant, seed, altered_dir=altered, spp=TARGET_SPP
        )
        if image is None:
            continue
        save_pair(
            folder / _name(scene.id, seed, target.index, variant),
            image.image,
            rendered,
            target.annotations.camera,
            scene.spec.camera.radius,
            fit_focal=not target.intrinsics_given,
            variant=variant,
            band=target.band,
        )


def _errors(case: dict[str, Any], near: np.ndarray | None) -> tuple[float, float]:
    """One refinement's position error (share of the radius) and rotation error (°)."""
    truth: PinholeCamera = case["truth"]
    fit = refine_dense(
        case["target"],
        case["rgb"],
        case["depth"],
        case["camera"],
        fit_focal=bool(case["fit_focal"]),
        near=near,
    )
    moved = float(np.linalg.norm(fit.position - np.asarray(truth.position))) / case["radius"]
    return moved, rotation_angle_deg(fit.rotation, np.asarray(truth.rotation))


def captured_cases(description: str) -> Path:
    """The cases folder of the command line (``--cases``, ``--n``, ``--seeds``: module
    docstring), captured there if missing."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--cases", type=Path, default=Path.home() / ".cache/cosmos/dense-light")
    parser.add_argument("--n", type=int, default=8, help="targets drawn per scene (capture)")
    parser.add_argument("--seeds", default="1,5", help="seeds of the generated scenes")
    args = parser.parse_args()
    capture(args.cases, args.n, [int(s) for s in args.seeds.split(",")])
    folder: Path = args.cases
    return folder


def main() -> None:
    cases = captured_cases(__doc__.splitlines()[0])
    # (variant, band) -> method -> [n, within 5 %/2°, within 2 %/1°]; and fixed / broken
    table: dict[tuple[str, str], dict[str, list[int]]] = defaultdict(
        lambda: {m: [0, 0, 0] for m in METHODS}
    )
    changed: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for path in sorted(cases.glob("*.npz")):
        case = load_pair(path)
        variant = str(case["variant"])
        inside = {}
        for method, mask in zip(METHODS, (None, case["near"]), strict=True):
            moved, turned = _errors(case, mask)
            inside[method] = moved <= 0.05 and turned <= 2.0
            for key in ((variant, str(case["band"])), (variant, "all")):
                row = table[key][method]
                row[0] += 1
                row[1] += inside[method]
                row[2] += moved <= 0.02 and turned <= 1.0
        counts = changed[variant]
        counts[0] += inside["outline"] and not inside["all edges"]
        counts[1] += inside["all edges"] and not inside["outline"]
    print("variant  band    n   all edges ≤5%/2° · ≤2%/1°   outline ≤5%/2° · ≤2%/1°")
    for (variant, band), rows in sorted(table.items()):
        n = rows[METHODS[0]][0]
        shares = [f"{r[1] / n:6.0%} · {r[2] / n:4.0%}" for r in (rows[m] for m in METHODS)]
        print(f"{variant:8s} {band:6s} {n:3d}   {shares[0]:>22s}   {shares[1]:>22s}")
    for variant, (fixed, broken) in sorted(changed.items()):
        print(
            f"{variant}: the outline put {fixed} inside 5 %/2° that all edges left out, "
            f"{broken} the reverse"
        )


if __name__ == "__main__":
    main()
