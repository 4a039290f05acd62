"""The paper mapping's lateral coefficients (eq. 5–6): fitting, storing and looking them up.

Eq. 5–6 model the lateral offset of an object from the scene centre, across the view, as linear
in the box centre's column ``u`` with a slope and an intercept that are themselves linear in its
row ``v`` (camera pixels, see :mod:`services.optimizer.mapping`):

.. math:: Δy = (a_s v + b_s)(u - u_c) + (a_i v + b_i).

For a pinhole camera over a ground plane the true slope is ``Z(v) / f`` with ``Z`` the depth of
the ground point seen at row ``v`` — a function of the camera's height, so of θ — and the linear
model is a first-order fit of it. The coefficients are therefore fitted per camera configuration
*and* per polar angle θ (the paper fixed one camera height): ordinary least squares over
calibration samples at each calibration θ, and linear interpolation in θ between them
(clamped at the ends). Eq. 4 also needs the height of the plane the box centres lie in, one
more fitted constant (:func:`fit_reference_height`). The samples come from rendered views with
the renderer's ground truth (``tools/fit_paper_mapping.py``); the fit itself is plain numpy and
lives here.

A camera configuration is (horizontal fov, aspect ratio, hemisphere radius). Coefficients are in
the pixels of the calibration width; a camera of the same fov and aspect at another resolution
uses them through the paper's scale ``s = W_cal / W``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike

from services.common.geometry.scene import CameraSpec
from services.optimizer.geometry import FloatArray

__all__ = [
    "DEFAULT_CALIBRATION_FILE",
    "CalibrationStore",
    "CalibrationSamples",
    "PaperCalibration",
    "fit_lateral",
    "fit_reference_height",
]

DEFAULT_CALIBRATION_FILE: Final = Path(__file__).with_name("paper_mapping.json")
_FORMAT_VERSION: Final = 1
_MATCH_TOL: Final = 1e-6


@dataclass(frozen=True)
class CalibrationSamples:
    """Calibration samples at one θ: box centres (camera pixels) and true offsets.

    Attributes
    ----------
    u, v : ndarray, shape (n,)
        Box centre column and row in pixels of the calibration camera.
    lateral : ndarray, shape (n,)
        True offset ``Δy = p · e₂`` of the object's footprint centre along the image's right
        axis, scene units.
    depth : ndarray, shape (n,)
        True depth offset ``Δx = −p · e₁`` beyond the scene centre, scene units.
    """

    u: FloatArray
    v: FloatArray
    lateral: FloatArray
    depth: FloatArray


def fit_reference_height(
    samples: dict[float, CalibrationSamples], radius: float, focal_px: float, cy: float
) -> float:
    """The height ``h`` of the plane the box centres lie in, for eq. 4 (robust fit).

    Eq. 4 intersects the ray through the box centre with a horizontal plane. The paper's balls
    all have their centres at one height, and its camera height ``y_c`` is measured to that
    plane; for a scene of unknown objects that height is a calibration constant. Each sample
    implies one: the ray dips β below the horizontal (eq. 2–3) and passes above the true
    footprint centre, at ground distance ``D = r sin θ + Δx`` from the camera's foot, at height

    .. math:: h_i = r \\cos θ − D_i \\tan β_i ,

    and ``h`` is their median (least squares weighted by ``1 / cot² β`` gives their mean; the
    median also shrugs off the near-horizon rays, where ``tan β`` amplifies every pixel).
    """
    implied: list[FloatArray] = []
    for theta_deg, sample in samples.items():
        theta = np.radians(theta_deg)
        beta = np.pi / 2.0 - theta + np.arctan((sample.v - cy) / focal_px)
        distance = radius * np.sin(theta) + sample.depth
        implied.append(radius * np.cos(theta) - distance * np.tan(beta))
    values = np.concatenate(implied) if implied else np.zeros(0)
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise ValueError("no samples to fit the reference height")
    return float(np.median(values))


def fit_lateral(samples: CalibrationSamples, cx: float) -> tuple[FloatArray, float]:
    """Least-squares ``(a_s, b_s, a_i, b_i)`` of eq. 5–6 and the fit's RMS residual.

    The model is linear in the four coefficients with design row
    ``(v (u − u_c), u − u_c, v, 1)``, solved with :func:`numpy.linalg.lstsq`.

    Raises
    ------
    ValueError
        With fewer than four samples (the fit would be undetermined).
    """
    du = samples.u - cx
    design = np.stack([samples.v * du, du, samples.v, np.ones_like(du)], axis=1)
    if design.shape[0] < 4:
        raise ValueError(f"need at least 4 samples to fit eq. 5-6, got {design.shape[0]}")
    solution, *_ = np.linalg.lstsq(design, samples.lateral, rcond=None)
    coef = np.asarray(solution, dtype=np.float64)
    residual = design @ coef - samples.lateral
    return coef, float(np.sqrt(np.mean(residual**2)))


@dataclass(frozen=True, eq=False)
class PaperCalibration:
    """Fitted eq. 5–6 coefficients of one camera configuration at several polar angles.

    Compared and hashed by identity (it holds arrays), so results can be cached per calibration.

    Attributes
    ----------
    fov_deg, radius : float
        Horizontal field of view and hemisphere radius of the calibration camera.
    width, height : int
        Its image size; coefficients are in its pixels.
    reference_height : float
        Height of the plane of box centres in eq. 4 (:func:`fit_reference_height`).
    theta_deg : ndarray, shape (K,)
        Calibration polar angles, increasing.
    coefficients : ndarray, shape (K, 4)
        ``(a_s, b_s, a_i, b_i)`` at each θ.
    rms : ndarray, shape (K,)
        RMS residual of each fit, scene units.
    samples : ndarray of int, shape (K,)
        Samples behind each fit.
    scenes : tuple of str
        Scenes the samples were rendered from.
    """

    fov_deg: float
    radius: float
    width: int
    height: int
    reference_height: float
    theta_deg: FloatArray
    coefficients: FloatArray
    rms: FloatArray
    samples: np.ndarray[Any, np.dtype[np.int64]]
    scenes: tuple[str, ...]

    def matches(self, camera: CameraSpec) -> bool:
        """Whether ``camera`` has this configuration (same fov, radius and aspect ratio)."""
        return (
            math.isclose(camera.fov_deg, self.fov_deg, abs_tol=_MATCH_TOL)
            and math.isclose(camera.radius, self.radius, rel_tol=_MATCH_TOL)
            and camera.width * self.height == camera.height * self.width
        )

    def scale(self, camera: CameraSpec) -> float:
        """The paper's scale ``s``: calibration pixels per pixel of ``camera``."""
        return self.width / camera.width

    def lateral_coefficients(self, theta_deg: ArrayLike) -> FloatArray:
        """``(..., 4)`` coefficients at ``theta_deg``, linear in θ between calibration angles and
        clamped beyond them."""
        theta = np.asarray(theta_deg, dtype=np.float64)
        columns = [np.interp(theta, self.theta_deg, self.coefficients[:, i]) for i in range(4)]
        return np.stack(columns, axis=-1)

    def to_json(self) -> dict[str, Any]:
        return {
            "camera": {
                "fov_deg": self.fov_deg,
                "width": self.width,
                "height": self.height,
                "radius": self.radius,
            },
            "scenes": list(self.scenes),
            "reference_height": self.reference_height,
            "rings": [
                {
                    "theta_deg": float(t),
                    "a_s": float(c[0]),
                    "b_s": float(c[1]),
                    "a_i": float(c[2]),
                    "b_i": float(c[3]),
                    "rms": float(r),
                    "samples": int(n),
                }
                for t, c, r, n in zip(
                    self.theta_deg, self.coefficients, self.rms, self.samples, strict=True
                )
            ],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PaperCalibration:
        camera = data["camera"]
        rings = sorted(data["rings"], key=lambda ring: float(ring["theta_deg"]))
        if not rings:
            raise ValueError("a calibration needs at least one ring")
        return cls(
            fov_deg=float(camera["fov_deg"]),
            radius=float(camera["radius"]),
            width=int(camera["width"]),
            height=int(camera["height"]),
            reference_height=float(data["reference_height"]),
            theta_deg=np.array([float(r["theta_deg"]) for r in rings]),
            coefficients=np.array(
                [[float(r[k]) for k in ("a_s", "b_s", "a_i", "b_i")] for r in rings]
            ),
            rms=np.array([float(r["rms"]) for r in rings]),
            samples=np.array([int(r["samples"]) for r in rings], dtype=np.int64),
            scenes=tuple(str(s) for s in data.get("scenes", ())),
        )


@dataclass(frozen=True)
class CalibrationStore:
    """Every stored paper calibration; looked up by camera configuration."""

    calibrations: tuple[PaperCalibration, ...] = ()

    def find(self, camera: CameraSpec) -> PaperCalibration | None:
        """The calibration of ``camera``'s configuration, or None."""
        for calibration in self.calibrations:
            if calibration.matches(camera):
                return calibration
        return None

    def __len__(self) -> int:
        return len(self.calibrations)

    @classmethod
    def load(cls, path: Path = DEFAULT_CALIBRATION_FILE) -> CalibrationStore:
        """Read a store written by :meth:`save`; a missing file is an empty store."""
        if not path.is_file():
            return cls()
        data = json.loads(path.read_text(encoding="utf-8"))
        if data.get("version") != _FORMAT_VERSION:
            raise ValueError(f"{path}: unsupported calibration format {data.get('version')!r}")
        return cls(tuple(PaperCalibration.from_json(c) for c in data["calibrations"]))

    def save(self, path: Path) -> None:
        payload = {
            "version": _FORMAT_VERSION,
            "note": "eq. 5-6 coefficients fitted by tools/fit_paper_mapping.py; do not edit",
            "calibrations": [c.to_json() for c in self.calibrations],
        }
        path.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")

    def replaced(self, calibration: PaperCalibration) -> CalibrationStore:
        """This store with ``calibration`` added, replacing one of the same configuration."""
        kept = tuple(
            c
            for c in self.calibrations
            if not (
                math.isclose(c.fov_deg, calibration.fov_deg, abs_tol=_MATCH_TOL)
                and math.isclose(c.radius, calibration.radius, rel_tol=_MATCH_TOL)
                and c.width * calibration.height == c.height * calibration.width
            )
        )
        return CalibrationStore((*kept, calibration))
