"""Camera poses on the hemisphere, as messages: angles, grid indices, and a query of either.

The maths of poses and of the grid lives in :mod:`services.common.geometry.grid`.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import ConfigDict, field_validator, model_validator

from services.common.base import Angle, FrozenModel, NonNegInt, ThetaDeg

__all__ = ["GridIndex", "Pose", "PoseQuery"]


class Pose(FrozenModel):
    """A camera pose on the hemisphere (paper eq. 1).

    ``theta_deg`` is the polar angle from the zenith (+z), ``phi_deg`` the azimuth from +x
    counter-clockwise seen from above, normalised to [0, 360). The camera sits at
    ``radius * (sin θ cos φ, sin θ sin φ, cos θ)`` and looks at the origin.
    """

    theta_deg: ThetaDeg
    phi_deg: Angle

    @field_validator("phi_deg")
    @classmethod
    def _wrap_phi(cls, value: float) -> float:
        wrapped = math.fmod(value, 360.0)
        if wrapped < 0.0:
            wrapped += 360.0
        # fmod of a tiny negative number can land exactly on 360.0 after the addition.
        return 0.0 if wrapped >= 360.0 else wrapped


class GridIndex(FrozenModel):
    """A grid pose by indices: ``lat`` counts rings from the lowest θ in range, ``lon`` counts
    positions on that ring from φ = 0 counter-clockwise."""

    lat: NonNegInt
    lon: NonNegInt


def _pose_query_schema(schema: dict[str, Any]) -> None:
    """Publish exactly what :class:`PoseQuery` accepts: the keys of one form, never null."""
    for prop in schema["properties"].values():
        variants = [v for v in prop.pop("anyOf", []) if v.get("type") != "null"]
        if variants:
            prop.update(variants[0])
        prop.pop("default", None)

    def form(keys: tuple[str, str], others: tuple[str, str]) -> dict[str, Any]:
        return {"required": list(keys), "not": {"anyOf": [{"required": [k]} for k in others]}}

    angles, indices = ("theta_deg", "phi_deg"), ("lat", "lon")
    schema["oneOf"] = [form(angles, indices), form(indices, angles)]


class PoseQuery(FrozenModel):
    """A pose in a request: either angles (``theta_deg`` and ``phi_deg``) or grid indices
    (``lat`` and ``lon``), not both."""

    model_config = ConfigDict(json_schema_extra=_pose_query_schema)

    theta_deg: ThetaDeg | None = None
    phi_deg: Angle | None = None
    lat: NonNegInt | None = None
    lon: NonNegInt | None = None

    @field_validator("theta_deg", "phi_deg", "lat", "lon", mode="before")
    @classmethod
    def _not_null(cls, value: object) -> object:
        if value is None:
            raise ValueError("must be a number, not null")
        return value

    @model_validator(mode="after")
    def _one_form(self) -> PoseQuery:
        angles = (self.theta_deg is not None, self.phi_deg is not None)
        indices = (self.lat is not None, self.lon is not None)
        if any(angles) and any(indices):
            raise ValueError("give either theta_deg/phi_deg or lat/lon, not both")
        if any(angles) and not all(angles):
            raise ValueError("theta_deg and phi_deg go together")
        if any(indices) and not all(indices):
            raise ValueError("lat and lon go together")
        if not any(angles) and not any(indices):
            raise ValueError("give theta_deg/phi_deg or lat/lon")
        return self

    def as_pose(self) -> Pose | None:
        """The angles as a :class:`Pose`, or None for a grid query."""
        if self.theta_deg is None or self.phi_deg is None:
            return None
        return Pose(theta_deg=self.theta_deg, phi_deg=self.phi_deg)

    def as_index(self) -> GridIndex | None:
        """The grid indices, or None for an angle query."""
        if self.lat is None or self.lon is None:
            return None
        return GridIndex(lat=self.lat, lon=self.lon)
