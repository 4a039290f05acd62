"""Detections' labels checked against the colours the detector measured.

A scene's own detector names an object's identity class, and the pose solver trusts it
(:func:`~.hypotheses.label_costs`). It can be wrong where the scene has changed: with the demo's
red ball left out of a photo, its model named the magenta ball ``red`` (0.81), and the solve
paired it with the red ball's place, 180 % of the radius off. The detector also measures each
object's mean colour (``Detection.color``, sRGB), and the scene file gives each untextured
object's linear-RGB ``color`` (a textured one's is its texture's mean: :mod:`.objects`).
Compared as chromaticities of linear RGB, ``c / (r + g + b)``, which a white light's shading
and the photo's exposure leave in place; its tone curve does not, so the measured colour is
taken to the power that brings it nearest, within :data:`TONE_GAMMA` either way:

.. math:: d_{ij} = \\min_{Γ^{-1} \\le γ \\le Γ}
    \\lVert χ(\\mathrm{lin}(m_i)^γ) - χ(ρ_j) \\rVert_2

with ``m_i`` the measured colour, ``lin`` the sRGB decoding (channel-wise powers), ``ρ_j`` the
object's colour and ``Γ`` = :data:`TONE_GAMMA`. A power changes a colour's saturation, not which
channel leads: on the free bench's ``photo`` targets (``cosmos bench --free --scene garden
--target-width 1280 --seed 41``, #2, gamma 0.8-1.25 drawn), the garden's red ball, which its
model named ``duck``, measured 0.063 from its own colour with γ = 1 and 0.008 with the
power, and the green post named ``arch`` 0.068 and 0.007: past :data:`AGREES` with γ = 1, so
the solve could pair neither with its object and answered 209 % of the radius off.
Replayed on four runs (``benchmarks.free_replay --all-variants``: the RESULTS run of seed 21,
the garden's seeds 31 and 32, and seed 41 at 1280 px; 380 targets), the own models' box
estimates within 10 %/5° went 211 → 213 of 300 and within 5 %/2° 175 → 176 (that view 209 % →
6 %), none lost; the general model's 36 and 21 of 80 stayed.

A detection whose colour is far from every object its label names (``d ≥``
:data:`CONTRADICTED`) and close to another object (``d ≤`` :data:`AGREES`) may also be that
object, at :data:`RELABEL_COST`, and :data:`~.hypotheses.SHAPE_MISMATCH_COST` more when that
object's shape is another; its label's objects stay compatible, so the geometry decides and
nothing the label allowed is lost. Drone views are not the hemisphere views a scene's model was
trained on, and it mistakes shapes there too: on a held-out garden view (the free bench's seed
27) it named the green post an ``arch``. Allowed only objects of the label's shape, then:
replayed on seven free bench runs (``benchmarks.free_replay --dump``, 1,080 targets), the own
models' box estimates within 5 %/2° went 267 → 272 of 440 (10–30° 87 → 89, 30–60° 92 → 94,
nadir 20 → 21), within 10 %/5° 317 → 322 (one lost, a garden view 6 % off that went to 12 %,
both ``ambiguous``); ``found`` 189 → 192 (found yet outside 5 %/2°: 16 before this and the
texture colours, 16 after).

Measured on the free bench's targets (seed 1; the demo and garden with their own detectors, two
generated scenes with the general model; clean, JPEG, noise, another light and a changed scene;
``d`` of each detection to its true object): at most 0.012 clean, 0.054 under JPEG, 0.024 with
noise, 0.29 under another light (whose shading of a red ball came 0.20 from the scene's
orange); between the demo's and the garden's distinct colours, at least 0.3. Dark colours
(:data:`DARK_SUM`) say little and are not used.

The general model names a shape class, wrong on most shapes it never saw (a generated scene's
meshes come out as cubes, cylinders, spheres or cones), so any object may be its detection's,
one of another shape at a price (:data:`~.hypotheses.SHAPE_MISMATCH_COST`). Its colour is
better evidence: on seed 21's generated scenes, 90 % of the general model's detections lay
within 0.07-0.09 of their object's colour (every variant; another light 0.093), while their
shape label was wrong on half of them. So a general-model pairing pays for its colour
distance too, :data:`COLOUR_COST` ``· min(d / CONTRADICTED, 1)``, and none for a wrong shape
when the colour agrees (``d ≤`` :data:`AGREES`): still evidence, not proof (a box on part of an
object, or on two, measured up to 0.6 from its object), and the geometry decides between
poses that pair alike. With the border's cut boxes paired by their visible part
(:mod:`.hypotheses`), through the stack on held-out seeds 26 and 27 (``cosmos bench --free
--scene demo,garden --random-scenes 3 --n 8 --onboard none``, one run each way): the general
model within 5 %/2° 136 → 158 of 240, renders 581 → 529, confirmed wrong 1 → 1 (the same
answer, 4.0 % / 2.2° off); the own models 131 → 130 of 160 (docs/EVALUATION.md).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from services.optimizer.free.hypotheses import SHAPE_MISMATCH_COST
from services.optimizer.free.objects import SceneObjects
from services.optimizer.free.srgb import linear
from services.optimizer.geometry import FloatArray

__all__ = [
    "AGREES",
    "COLOUR_COST",
    "CONTRADICTED",
    "DARK_SUM",
    "RELABEL_COST",
    "TONE_GAMMA",
    "TONE_SAMPLES",
    "colour_distances",
    "recoloured",
]

CONTRADICTED: Final = 0.15
"""A label is contradicted when the detection's chromaticity is at least this far from every
object it names (module docstring: JPEG moves it 0.05 at most, another light 0.29)…"""
AGREES: Final = 0.06
"""…and it may be another object within this distance of its chromaticity."""
TONE_GAMMA: Final = 1.2
"""A photo's tone curve is not the renderer's sRGB: the measured colour's linear values are
taken to any power within this factor either way (display gammas of 1.8 to 2.6 against sRGB's
2.2), and the distance is the least over them (module docstring)…"""
TONE_SAMPLES: Final = 9
"""…sampled at this many powers, evenly in log (steps of 4.7 %)."""
DARK_SUM: Final = 90.0
"""Measured colours whose sRGB channels sum below this (of 765) are not compared."""
RELABEL_COST: Final = 0.25
"""Pairing cost, in gate units, of a detection with the object its colour names instead of its
label (as a general-model detection with an object of another shape)."""
COLOUR_COST: Final = 0.5
"""A general-model pairing's cost, in gate units, at a colour distance of :data:`CONTRADICTED`
or more (less in proportion below it): twice a wrong shape's, under an unpaired detection's."""


def _chromaticity(rgb: FloatArray) -> FloatArray:
    total = rgb.sum(axis=-1, keepdims=True)
    out: FloatArray = rgb / np.where(total > 1e-9, total, np.nan)
    return out


def colour_distances(measured: ArrayLike, objects: SceneObjects) -> FloatArray:
    """(D, M) chromaticity distance ``d_ij`` (module docstring) of measured sRGB colours
    ``(D, 3)`` (0–255, NaN when not measured) to the objects' colours; NaN where either is
    unknown or the measured colour is dark."""
    m = np.asarray(measured, dtype=np.float64).reshape(-1, 3)
    if objects.colors is None:
        return np.full((len(m), len(objects)), np.nan)
    gammas = np.geomspace(1.0 / TONE_GAMMA, TONE_GAMMA, TONE_SAMPLES)
    toned = linear(np.clip(m, 0.0, 255.0) / 255.0)[None, :, :] ** gammas[:, None, None]
    seen = _chromaticity(toned)
    seen[:, ~(m.sum(axis=1) >= DARK_SUM)] = np.nan
    known = _chromaticity(np.asarray(objects.colors, dtype=np.float64))
    gaps = np.linalg.norm(seen[:, :, None, :] - known[None, None, :, :], axis=-1)
    distances: FloatArray = gaps.min(axis=0)
    return distances


def recoloured(
    costs: FloatArray, objects: SceneObjects, general: ArrayLike, measured: ArrayLike
) -> FloatArray:
    """``costs`` (:func:`~.hypotheses.label_costs`, (D, M)) with each own-detector detection
    (``general`` false) whose colour contradicts its label also compatible with the objects
    that its colour names, and each general-model detection's pairings priced by their colour
    distance (module docstring)."""
    out = np.array(costs, dtype=np.float64)
    d = colour_distances(measured, objects)
    shapes = np.array(objects.shapes, dtype=object)
    by_shape = np.asarray(general, dtype=np.bool_)
    for i in np.flatnonzero(~by_shape):
        named = np.isfinite(out[i])
        if not named.any() or not np.all(d[i, named] >= CONTRADICTED):
            continue
        agrees = ~named & (d[i] <= AGREES)
        reshaped = ~np.isin(shapes, shapes[named])
        out[i, agrees] = RELABEL_COST + np.where(reshaped[agrees], SHAPE_MISMATCH_COST, 0.0)
    known = np.isfinite(d[by_shape])
    rows = out[by_shape]
    rows = np.where(known & (d[by_shape] <= AGREES) & np.isfinite(rows), 0.0, rows)
    colour = np.minimum(np.where(known, d[by_shape], 0.0) / CONTRADICTED, 1.0)
    out[by_shape] = rows + COLOUR_COST * colour
    return out
