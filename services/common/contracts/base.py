"""The base of every shared message, and the constrained types several stages use.

Every model is frozen and strict about unknown keys, so a typo in a request is an error, not a
silently ignored field.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Angle", "BoxXYXY", "FrozenModel", "NonNegInt", "ThetaDeg"]


class FrozenModel(BaseModel):
    """Base of all shared messages: immutable, unknown keys rejected, NaN/inf rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Angle = Annotated[float, Field(allow_inf_nan=False)]
"""An angle in degrees, any finite value."""

ThetaDeg = Annotated[float, Field(ge=0.0, le=90.0, allow_inf_nan=False)]
"""A polar angle from the zenith in degrees, 0 ≤ θ ≤ 90."""

NonNegInt = Annotated[int, Field(ge=0)]

BoxXYXY = tuple[float, float, float, float]
"""A pixel box ``[x1, y1, x2, y2]`` (pixel edges)."""
