"""The focal lengths a free search considers when the photo's intrinsics are not known.

Without them, distance and focal length trade along a valley (a dolly zoom) that runs on
towards the orthographic limit: boxes, and edges too where the view hardly shows perspective
(seen from above, a flat layout), fit ever narrower lenses from ever farther away about as
well. So a fitted focal length ``f`` is sought within :data:`FOCAL_BOUNDS` of the scene
camera's ``f₀``,

.. math:: b_0 f_0 \\le f \\le b_1 f_0,

and a fit that ends on a bound or beyond (:func:`at_bound`) has not found the focal length: the
data would take it further, and the caller keeps a focal length it did not fit. The box solve's
fits are bounded so whatever fit they start from (:func:`zoom_bounds`: each start's own bounds
let refits step on along the valley); the dense fit keeps its bounds about its start, which it
then checks.
"""

from __future__ import annotations

import math
from typing import Final

__all__ = ["AT_BOUND", "FOCAL_BOUNDS", "at_bound", "zoom_bounds"]

FOCAL_BOUNDS: Final = (0.5, 2.0)
"""The least and greatest focal length as factors of the scene camera's: a horizontal field of
view of 45° stays between about 23° and 79°. Unbounded, a general-model fit on wrong pairs ran
off to a camera 2400 scene units away at a 0.1° field of view (seed 5 of the free bench).
Bounded only from each fit's start, refits stepped on: a nadir view of a generated scene
(``cosmos bench --free --scene demo --random-scenes 2 --n 8 --seed 21``, ``rand21-0`` #7, its own
detector) was answered at a 10° field of view (5.7 times the scene camera's focal length), 6
radii from the truth, and a dense fit of a 60–89° view of the same scene at 119° (truth 60°)."""
AT_BOUND: Final = 1e-3
"""A fitted focal length this close (in log) to a bound ran into it."""


def zoom_bounds(start: float, reference: float) -> tuple[float, float]:
    """The zooms of a ``start`` focal length (pixels) that a fit may reach: within
    :data:`FOCAL_BOUNDS` of the ``reference`` (the scene camera's, same pixels), however far the
    start is from it; 1 always included, so that the start is a feasible point."""
    low = FOCAL_BOUNDS[0] * reference / start
    high = FOCAL_BOUNDS[1] * reference / start
    return min(low, 1.0), max(high, 1.0)


def at_bound(fitted: float, reference: float) -> bool:
    """Whether a ``fitted`` focal length ended on a bound of :data:`FOCAL_BOUNDS` about the
    ``reference`` (within :data:`AT_BOUND` in log) or beyond it (where a dense fit, bounded
    about its start, may end)."""
    zoom = math.log(fitted / reference)
    low, high = (math.log(b) for b in FOCAL_BOUNDS)
    return zoom <= low + AT_BOUND or zoom >= high - AT_BOUND
