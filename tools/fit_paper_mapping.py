"""Fit the paper mapping's lateral coefficients (eq. 5–6) on rendered views and store them.

Run ``python -m tools.fit_paper_mapping [--scenes demo garden] [--azimuths 24] [--out PATH]``.
For every polar angle θ = 0, Δ, 2Δ … 90° (Δ the scenes' grid step) and ``--azimuths`` evenly
spaced φ, the render engine annotates the view with exact ground truth (footprint centres and
visible boxes). Every wholly visible object whose box the image border does not cut is one
sample: its box centre ``(u, v)`` and its true lateral offset ``q₂ = p · e₂`` along the image's
right axis. Coefficients are fitted per θ by least squares
(:func:`services.optimizer.calibration.fit_lateral`) and written to
``services/optimizer/paper_mapping.json`` under the scenes' camera configuration; the scenes
must share one camera.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.geometry.camera import focal_length_px
from services.common.geometry.pose import Pose
from services.common.geometry.scene import CameraSpec, LoadedScene
from services.optimizer.calibration import (
    DEFAULT_CALIBRATION_FILE,
    CalibrationSamples,
    CalibrationStore,
    PaperCalibration,
    fit_lateral,
    fit_reference_height,
)
from services.optimizer.mapping import clipped_sides
from services.renderer.engine import RenderEngine

__all__ = ["calibration_thetas", "collect_samples", "fit_calibration", "main"]


def calibration_thetas(step_deg: float) -> list[float]:
    """Polar angles 0, Δ, 2Δ … up to 90° inclusive."""
    count = int(np.floor(90.0 / step_deg + 1e-9))
    return [round(k * step_deg, 9) for k in range(count + 1)]


def collect_samples(
    engine: RenderEngine,
    scenes: Sequence[LoadedScene],
    thetas: Sequence[float],
    azimuths: int,
) -> dict[float, CalibrationSamples]:
    """Annotated samples per θ from ``azimuths`` views per scene (see the module docstring)."""
    samples: dict[float, CalibrationSamples] = {}
    for theta in thetas:
        u: list[float] = []
        v: list[float] = []
        lateral: list[float] = []
        depth: list[float] = []
        for scene in scenes:
            camera = scene.spec.camera
            for phi in np.arange(azimuths) * 360.0 / azimuths:
                pose = Pose(theta_deg=theta, phi_deg=float(phi))
                ann = engine.annotate(scene, pose, camera.width, camera.height, None)
                e1 = np.array([np.cos(np.radians(phi)), np.sin(np.radians(phi))])
                e2 = np.array([-e1[1], e1[0]])
                for obj in ann.objects:
                    if obj.box is None or obj.visible_fraction < 0.99:
                        continue
                    if clipped_sides([obj.box], camera.width, camera.height).any():
                        continue
                    x1, y1, x2, y2 = obj.box
                    u.append((x1 + x2) / 2.0)
                    v.append((y1 + y2) / 2.0)
                    lateral.append(float(np.dot(obj.position[:2], e2)))
                    depth.append(-float(np.dot(obj.position[:2], e1)))
        samples[theta] = CalibrationSamples(
            u=np.array(u), v=np.array(v), lateral=np.array(lateral), depth=np.array(depth)
        )
    return samples


def fit_calibration(
    samples: dict[float, CalibrationSamples], camera: CameraSpec, scenes: Sequence[str]
) -> PaperCalibration:
    """One least-squares fit of eq. 5–6 per θ (θ with fewer than 4 samples are skipped)."""
    thetas, coefficients, rms, counts = [], [], [], []
    for theta in sorted(samples):
        sample = samples[theta]
        if len(sample.u) < 4:
            continue
        coef, residual = fit_lateral(sample, camera.width / 2.0)
        thetas.append(theta)
        coefficients.append(coef)
        rms.append(residual)
        counts.append(len(sample.u))
    if not thetas:
        raise ValueError("no θ had enough samples to fit")
    focal = focal_length_px(camera.fov_deg, camera.width)
    return PaperCalibration(
        fov_deg=camera.fov_deg,
        radius=camera.radius,
        width=camera.width,
        height=camera.height,
        reference_height=fit_reference_height(samples, camera.radius, focal, camera.height / 2.0),
        theta_deg=np.array(thetas),
        coefficients=np.array(coefficients),
        rms=np.array(rms),
        samples=np.array(counts, dtype=np.int64),
        scenes=tuple(scenes),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Collect, fit, print and store; return the process exit status."""
    parser = argparse.ArgumentParser(prog="python -m tools.fit_paper_mapping", description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["demo", "garden"])
    parser.add_argument("--azimuths", type=int, default=24, help="views per θ and scene")
    parser.add_argument("--out", type=Path, default=DEFAULT_CALIBRATION_FILE)
    args = parser.parse_args(argv)
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    scenes = [catalog.get(scene_id) for scene_id in args.scenes]
    cameras = {scene.spec.camera for scene in scenes}
    if len(cameras) != 1:
        print("the scenes must share one camera configuration", file=sys.stderr)
        return 2
    camera = scenes[0].spec.camera
    step = min(scene.spec.search.angle_step_deg for scene in scenes)
    engine = RenderEngine("auto")
    engine.start()
    try:
        samples = collect_samples(engine, scenes, calibration_thetas(step), args.azimuths)
    finally:
        engine.close()
    calibration = fit_calibration(samples, camera, args.scenes)
    print(f"camera fov={camera.fov_deg}° {camera.width}x{camera.height} r={camera.radius}")
    print(f"reference height of box centres (eq. 4): {calibration.reference_height:.4f}")
    print(f"{'θ°':>6} {'a_s':>11} {'b_s':>11} {'a_i':>11} {'b_i':>11} {'rms':>7} {'n':>5}")
    for theta, coef, rms, n in zip(
        calibration.theta_deg,
        calibration.coefficients,
        calibration.rms,
        calibration.samples,
        strict=True,
    ):
        print(
            f"{theta:6.1f} {coef[0]:11.3e} {coef[1]:11.3e} {coef[2]:11.3e} {coef[3]:11.3e} "
            f"{rms:7.4f} {n:5d}"
        )
    store = CalibrationStore.load(args.out).replaced(calibration)
    store.save(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
