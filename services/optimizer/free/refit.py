"""Whether a dense fit is worth one more render at it, and a refit from there.

A dense fit (:mod:`.dense`) aligns the edges of a render made at its start. Its silhouettes and
occlusions belong to that render's viewpoint: a fit that moved far from it aligned edges the
target does not show, and one more render at the fit removes that bias.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from services.common.geometry.camera import PinholeCamera
from services.optimizer.free.dense import DenseFit

__all__ = ["REFIT_MOVE", "REFIT_SHARE", "REFIT_ZOOM", "worth_another_render"]

REFIT_ZOOM: Final = 0.06
"""A fit whose focal length moved more than this share from the render's, or whose camera
moved more than this share of the points' depth, is worth one more render
(:func:`worth_another_render`). At 0.03 two thirds of the fits without given intrinsics asked
for one. Measured in process (``python -m cosmos.bench.free_targets --scene demo
--random-scenes 3 --n 12 --seed S``, S = 1-5: 80 targets without intrinsics, each in three
image variants, one run each way): at 0.06, 109 renders more instead of 160; within 5 %/2°
189 of 240 against 191, within 2 %/1° 149 against 150; every answer the same but one demo view
of four spheres from 60-89° (clean and JPEG, its fov 1.0 → 2.0 % off). A fit moved by no more
than that leans on the silhouettes of a render so near that a second one changes nothing."""
REFIT_MOVE: Final = 0.1
"""A fit of the pose alone (the focal length held) whose camera moved more than this share of
the points' depth, out of the near moves of ``refine_pose``'s ``MAX_MOVE``…"""
REFIT_SHARE: Final = 0.8
"""…and left fewer than this share of its edge points on the target's edges is worth one more
render (:func:`worth_another_render`); the share at which the controller takes a render's
edges as agreeing with the target."""


def worth_another_render(fit: DenseFit, camera: PinholeCamera) -> bool:
    """Whether to render once more at ``fit`` and refine again from there.

    The render's silhouettes and occlusions belong to its own viewpoint. Turning the camera
    about its centre leaves them as they are (the depth carries the points exactly), but moving
    it by ``δ`` changes the directions it sees the objects from by about ``δ / z̃`` radians,
    ``z̃`` the points' median depth; the fit then aligned edges the target does not show.

    * The focal length fitted: it moved more than :data:`REFIT_ZOOM` from the render's
      ``camera``, or the camera centre more than that share of ``z̃``. The silhouettes bias the
      focal length, which the distance follows: measured on free targets of generated scenes
      without given intrinsics (fov errors 5–10 % after one render), a second fit took most to
      within 2 %.
    * The pose alone: the camera centre moved more than :data:`REFIT_MOVE` of ``z̃``, and the
      fit left more than ``1 -`` :data:`REFIT_SHARE` of its edge points off the target's edges
      (the silhouettes, seen from that far, do not all match). Through the real stack (``cosmos
      bench --free --scene demo --random-scenes 2 --n 8 --seed 1``), the move alone asked for a
      render in 27 of 75 searches given their intrinsics, most of them general-model box poses
      that the first fit had already taken to within 1 %/0.5°, and the median search spent 2
      renders; one gained (11.8 %/4.5° → 2.0 %/0.8°), at a share of 0.75. In process (the
      targets given their intrinsics of ``python -m cosmos.bench.free_targets --scene demo
      --random-scenes 2 --n 8``, seeds 1 and 5, and ``--random-scenes 3 --seed 3``: exact boxes
      with the detector's noise, 150 fits), the fits that gained had left 0.67 of their points on
      the target's, those that moved as far and had nothing to gain 0.80-0.94.
    """
    shift = float(np.linalg.norm(fit.position - np.asarray(camera.position, dtype=np.float64)))
    if not fit.focal_fitted:
        return shift > REFIT_MOVE * fit.depth and fit.share() < REFIT_SHARE
    return abs(fit.intrinsics.fx / camera.fx - 1.0) > REFIT_ZOOM or shift > REFIT_ZOOM * fit.depth
