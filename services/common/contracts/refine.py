"""Messages of the optimizer's ``POST /refine-pose``: a free pose refined densely against the
target image by one render at it (issue 23, "confirmation and dense refinement by one render").

The body is ``multipart/form-data`` of three parts:

* ``request``: a :class:`RefinePoseRequest` as JSON text;
* ``target``: the target image (PNG, JPEG or binary PPM), at its own size;
* ``render``: the render at the request's pose as the renderer answers ``POST /render`` on
  ``Accept: application/x-npz`` (:mod:`services.common.depth_archive`: colours, depth, object
  ids), on the target's shape scaled by ``s`` (its film at most :data:`MAX_FILM_SCALE` times
  the target's size): the render's camera is the pose's with its pixel intrinsics scaled by
  ``s = render width / target width``.

The answer is a :class:`RefinePoseResponse`.

``POST /refine-pose/target`` makes ready, ahead of the render, what the refinements of a search
will need of its target (its grey image on the render's film and its distance maps), so that
the first refinement finds them: a form of a :class:`TargetRequest` (``request``) and the
``target``, answered by a :class:`TargetResponse`. An optimizer answers the refinements alike
with or without it.
"""

from __future__ import annotations

from typing import Annotated, Final

from pydantic import Field

from services.common.base import FrozenModel
from services.common.contracts.free import DenseReport, FreePose
from services.common.geometry.scene import SCENE_ID_PATTERN

__all__ = [
    "MAX_FILM_SCALE",
    "REFINE_PARTS",
    "TARGET_PARTS",
    "FocalCheck",
    "RefinePoseRequest",
    "RefinePoseResponse",
    "TargetRequest",
    "TargetResponse",
]

MAX_FILM_SCALE: Final = 2.0
"""The render's film is at most this many times the target's size: a small photo without its
intrinsics is refined on a film larger than itself, its grey upsampled, so that its edges are
located to within a fraction of its own pixels (the focal length is told from the distance by
a sub-pixel perspective effect)."""
REFINE_PARTS: Final = ("request", "target", "render")
"""The form's parts: the JSON request, the target image, the render's archive."""
TARGET_PARTS: Final = ("request", "target")
"""``POST /refine-pose/target``'s parts: the JSON request and the target image."""


class RefinePoseRequest(FrozenModel):
    """The ``request`` part: the ``scene``, the ``pose`` the render was made at (as ``POST
    /free-pose`` answered it, target pixels), whether to fit the focal length too
    (``fit_focal``: the photo's intrinsics were not given) and whether to check the pose's
    focal length (``check_focal``: it was stated, not given, as by the photo's EXIF): the pose
    is then fitted with it, and again with the focal length free from the same render
    (``RefinePoseResponse.focal_check``); ``fit_lens`` when the pose's lens (a radial ``k1``
    alone) is one a lens check estimated: the render was made through it, and the check fits
    it again from there (``RefinePoseResponse.lens_pose``)."""

    scene: Annotated[str, Field(pattern=SCENE_ID_PATTERN)]
    pose: FreePose
    fit_focal: bool = False
    check_focal: bool = False
    fit_lens: bool = Field(
        default=False,
        description="The pose's lens distortion (a radial k1 alone) is an estimate, as "
        "`lens_pose` answered it: fit k1 again with the pose.",
    )


class FocalCheck(FrozenModel):
    """The pose fitted with the focal length free, from the same render, as a check of the
    focal length the request's pose states: the ``pose`` it ends at (its intrinsics
    ``estimated`` when the edges pinned the focal length, its ``residual_px`` the fit's edge
    RMS) and how that fit went (``fit``)."""

    pose: FreePose
    fit: DenseReport


class RefinePoseResponse(FrozenModel):
    """The refined ``pose`` (its intrinsics ``estimated`` when the focal length was fitted, its
    ``residual_px`` the dense fit's edge RMS, its pairs' predicted boxes at the refined pose)
    and how the fit went (``fit``): use it only when ``fit.accepted``; ``focal_check`` when the
    request asked to check the pose's focal length (null from an optimizer that does not);
    ``lens_pose`` when the fit's lens check says the target's edges bend (``fit.lens.bends``):
    the pose it fitted with its radial ``k1`` (intrinsics ``estimated``, distortion ``k1``
    alone), else null."""

    pose: FreePose
    fit: DenseReport
    focal_check: FocalCheck | None = None
    lens_pose: FreePose | None = None


class TargetRequest(FrozenModel):
    """The ``request`` part of ``POST /refine-pose/target``: the ``film`` ``(width, height)``,
    in pixels, that the search's renders (and so its refinements) will be made on, and whether
    they will fit the focal length (``fit_focal``: every level of the distance maps is then
    needed, else the finest)."""

    film: tuple[Annotated[int, Field(ge=8, le=16_384)], Annotated[int, Field(ge=8, le=16_384)]]
    fit_focal: bool = False


class TargetResponse(FrozenModel):
    """What was made ready: the ``film`` and how many distance-map ``levels``; ``kept`` is false
    when the optimizer keeps no targets (its cache bound is 0, or the maps exceed it), and the
    refinements will make their own."""

    film: tuple[int, int]
    levels: int
    kept: bool
