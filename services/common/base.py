"""The base of every shared message, and the constrained types several stages use.

Every model is frozen and strict about unknown keys, so a typo in a request is an error, not a
silently ignored field. Numbers are strict too (:data:`Number`, :data:`Integer`): pydantic's lax
mode would read ``true`` as 1 and ``"45"`` as 45, and take integers no int64 holds.
"""

from __future__ import annotations

from typing import Annotated, Final

from pydantic import BaseModel, ConfigDict, Field, Strict

__all__ = [
    "MAX_SAFE_INTEGER",
    "Angle",
    "BoxXYXY",
    "FrozenModel",
    "Integer",
    "NonNegInt",
    "Number",
    "ThetaDeg",
]


class FrozenModel(BaseModel):
    """Base of all shared messages: immutable, unknown keys rejected, NaN/inf rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


MAX_SAFE_INTEGER: Final = 2**53 - 1
"""The largest integer every JSON client holds exactly (JavaScript's ``Number.MAX_SAFE_INTEGER``);
well inside int64, so numpy never overflows on one."""

Number = Annotated[float, Strict(), Field(allow_inf_nan=False)]
"""A finite number: a JSON integer or float, never a bool or a numeric string."""

Integer = Annotated[int, Strict(), Field(ge=-MAX_SAFE_INTEGER, le=MAX_SAFE_INTEGER)]
"""An integer within ±:data:`MAX_SAFE_INTEGER`: never a bool, a string or a float."""

Angle = Number
"""An angle in degrees, any finite value."""

ThetaDeg = Annotated[Number, Field(ge=0.0, le=90.0)]
"""A polar angle from the zenith in degrees, 0 ≤ θ ≤ 90."""

NonNegInt = Annotated[Integer, Field(ge=0)]

BoxXYXY = tuple[Number, Number, Number, Number]
"""A pixel box ``[x1, y1, x2, y2]`` (pixel edges)."""
