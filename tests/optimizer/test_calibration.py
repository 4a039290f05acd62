"""The paper mapping's fitted coefficients: refitting on fewer rendered samples agrees with the
stored file, and the fit and store behave."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import (
    CalibrationSamples,
    CalibrationStore,
    PaperCalibration,
    fit_lateral,
)
from tools.fit_paper_mapping import calibration_thetas, collect_samples, fit_calibration

CAMERA = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)


@pytest.fixture(scope="module")
def stored() -> PaperCalibration:
    calibration = CalibrationStore.load().find(CAMERA)
    assert calibration is not None, "run python -m tools.fit_paper_mapping"
    return calibration


@pytest.fixture(scope="module")
def refit(engine, catalog) -> PaperCalibration:
    scenes = [catalog.get("demo"), catalog.get("garden")]
    samples = collect_samples(engine, scenes, [15.0, 45.0, 67.5], azimuths=6)
    return fit_calibration(samples, CAMERA, ["demo", "garden"])


def lateral(coef: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return (coef[0] * v + coef[1]) * (u - 160.0) + (coef[2] * v + coef[3])


def test_refit_on_fewer_samples_agrees_with_the_stored_coefficients(stored, refit):
    u, v = np.meshgrid(np.linspace(40, 280, 13), np.linspace(40, 200, 9))
    for theta, coef in zip(refit.theta_deg, refit.coefficients, strict=True):
        ours = lateral(coef, u, v)
        theirs = lateral(stored.lateral_coefficients(theta), u, v)
        # Δy over the central image differs by a few centimetres at most (objects span ±3).
        assert np.sqrt(np.mean((ours - theirs) ** 2)) < 0.06, theta
    assert refit.reference_height == pytest.approx(stored.reference_height, abs=0.05)
    assert np.all(refit.rms < 0.1)


def test_stored_calibration_covers_the_full_hemisphere(stored):
    assert stored.theta_deg[0] == 0.0
    assert stored.theta_deg[-1] == 90.0
    assert np.all(np.diff(stored.theta_deg) > 0)
    assert set(stored.scenes) == {"demo", "garden"}
    assert calibration_thetas(7.5) == list(stored.theta_deg)


def test_fit_recovers_known_coefficients():
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 320, 50), rng.uniform(0, 240, 50)
    truth = np.array([-3e-5, 0.025, 2e-4, -0.05])
    samples = CalibrationSamples(u=u, v=v, lateral=lateral(truth, u, v), depth=np.zeros(50))
    coef, rms = fit_lateral(samples, 160.0)
    np.testing.assert_allclose(coef, truth, rtol=1e-8, atol=1e-12)
    assert rms < 1e-10
    with pytest.raises(ValueError, match="at least 4"):
        fit_lateral(CalibrationSamples(u[:3], v[:3], u[:3], u[:3]), 160.0)


def test_store_round_trip_and_lookup(tmp_path, stored):
    path = tmp_path / "coefficients.json"
    CalibrationStore((stored,)).save(path)
    loaded = CalibrationStore.load(path)
    assert json.loads(path.read_text())["version"] == 1
    again = loaded.find(CAMERA)
    assert again is not None
    np.testing.assert_allclose(again.coefficients, stored.coefficients)
    # Same fov and aspect at another resolution: usable through the paper's scale s.
    double = CameraSpec(fov_deg=45.0, width=640, height=480, radius=8.0)
    assert loaded.find(double) is again
    assert again.scale(double) == 0.5
    assert loaded.find(CameraSpec(fov_deg=60.0, width=320, height=240, radius=8.0)) is None
    assert loaded.find(CameraSpec(fov_deg=45.0, width=320, height=320, radius=8.0)) is None
    assert CalibrationStore.load(tmp_path / "missing.json").find(CAMERA) is None


def test_coefficients_interpolate_in_theta_and_clamp(stored):
    mid = stored.lateral_coefficients((stored.theta_deg[2] + stored.theta_deg[3]) / 2)
    np.testing.assert_allclose(mid, (stored.coefficients[2] + stored.coefficients[3]) / 2)
    np.testing.assert_allclose(stored.lateral_coefficients(-5.0), stored.coefficients[0])
