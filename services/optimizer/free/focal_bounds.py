"""The focal lengths a free search considers when the photo's intrinsics are not known.

Without them, distance and focal length trade along a valley (a dolly zoom) that runs on
towards the orthographic limit: boxes, and edges too where the view hardly shows perspective
(seen from above, a flat layout), fit ever narrower lenses from ever farther away about as
well. So a fitted focal length ``f`` (pixels) is sought within a :class:`FocalRange`: the
lenses a photo is likely taken with, whatever camera the scene file holds, and that camera's
own,

.. math:: \\min(b_0 f_0,\\; e_0 d / D) \\le f \\le \\max(b_1 f_0,\\; e_1 d / D),

with ``f₀`` the scene camera's focal length on the photo's film, ``(b₀, b₁)`` =
:data:`FOCAL_BOUNDS`, ``(e₀, e₁)`` = :data:`LENS_EQUIVALENT_MM` the 35 mm-equivalent focal
lengths of the lenses considered, ``d`` the film's diagonal in pixels and ``D`` = 43.27 mm the
35 mm frame's (a 35 mm-equivalent focal length is defined by the diagonal, so the range holds
for a photo of any shape, upright or not).

A fit that ends on a bound or beyond (:func:`at_bound`) has not found the focal length: the
data would take it further, and the caller keeps a focal length it did not fit. The box solve's
fits are bounded so whatever fit they start from (:func:`zoom_bounds`: each start's own bounds
let refits step on along the valley); the dense fit keeps its bounds about its start, which it
then checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from services.common.geometry.camera import fov_deg_of

__all__ = [
    "AT_BOUND",
    "FOCAL_BOUNDS",
    "FULL_FRAME_DIAGONAL_MM",
    "LENS_EQUIVALENT_MM",
    "FocalRange",
    "at_bound",
    "zoom_bounds",
]

FOCAL_BOUNDS: Final = (0.5, 2.0)
"""The least and greatest focal length as factors of the scene camera's: a horizontal field of
view of 45° stays between about 23° and 79°. Unbounded, a general-model fit on wrong pairs ran
off to a camera 2400 scene units away at a 0.1° field of view (seed 5 of the free bench).
Bounded only from each fit's start, refits stepped on: a nadir view of a generated scene
(``cosmos bench --free --scene demo --random-scenes 2 --n 8 --seed 21``, ``rand21-0`` #7, its own
detector) was answered at a 10° field of view (5.7 times the scene camera's focal length), 6
radii from the truth, and a dense fit of a 60–89° view of the same scene at 119° (truth 60°)."""
LENS_EQUIVALENT_MM: Final = (13.0, 80.0)
"""The 35 mm-equivalent focal lengths of the lenses a photo is taken with: a phone's or a
drone's ultra-wide (13 mm, 118° across the diagonal) to a short telephoto (80 mm, 30°). A
drone's main camera (24 mm: 84° diagonal, about 72° across a 4:3 photo) lies within, whatever
the scene file's camera; bounded only by :data:`FOCAL_BOUNDS`, a scene modelled with a 35°
camera could not estimate it (its widest was 64°)."""
FULL_FRAME_DIAGONAL_MM: Final = math.hypot(36.0, 24.0)
"""The 35 mm frame's diagonal, which defines a 35 mm-equivalent focal length."""
AT_BOUND: Final = 1e-3
"""A fitted focal length this close (in log) to a bound ran into it."""


@dataclass(frozen=True)
class FocalRange:
    """The least and greatest focal length (pixels of one film) a fit may take."""

    low: float
    high: float

    @classmethod
    def of(cls, reference: float, width: float, height: float) -> FocalRange:
        """The range on a ``width`` x ``height`` film whose scene camera has the focal length
        ``reference`` (pixels) there (module docstring)."""
        per_mm = math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
        low = min(FOCAL_BOUNDS[0] * reference, LENS_EQUIVALENT_MM[0] * per_mm)
        high = max(FOCAL_BOUNDS[1] * reference, LENS_EQUIVALENT_MM[1] * per_mm)
        return cls(low, high)

    @classmethod
    def about(cls, reference: float) -> FocalRange:
        """Within :data:`FOCAL_BOUNDS` of ``reference`` alone (a stated focal length checked)."""
        return cls(FOCAL_BOUNDS[0] * reference, FOCAL_BOUNDS[1] * reference)

    def fov_deg(self, width: float) -> tuple[float, float]:
        """The horizontal fields of view (degrees) of the range's ends on a film ``width``
        pixels wide: widest first."""
        return fov_deg_of(self.low, width), fov_deg_of(self.high, width)


def zoom_bounds(start: float, focal: FocalRange) -> tuple[float, float]:
    """The zooms of a ``start`` focal length (pixels) that a fit may reach: within ``focal``,
    however far the start is from it; 1 always included, so that the start is a feasible
    point."""
    return min(focal.low / start, 1.0), max(focal.high / start, 1.0)


def at_bound(fitted: float, focal: FocalRange) -> bool:
    """Whether a ``fitted`` focal length (pixels) ended on a bound of ``focal`` (within
    :data:`AT_BOUND` in log) or beyond it (where a dense fit, bounded about its start, may
    end)."""
    zoom = math.log(fitted)
    return zoom <= math.log(focal.low) + AT_BOUND or zoom >= math.log(focal.high) - AT_BOUND
