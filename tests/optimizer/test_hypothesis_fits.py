"""One solve's edge fits (services.optimizer.free.hypothesis_fits.EdgeFits): a start already
fitted is not fitted again, and only such a start shares the fit made then; a fitted focal
length stays within its bounds of the scene camera's."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import services.optimizer.free.hypothesis_fits as hypothesis_fits
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera
from services.optimizer.free import Intrinsics, project_boxes, scene_objects
from services.optimizer.free.focal_bounds import FOCAL_BOUNDS, FocalRange, at_bound
from services.optimizer.free.hypothesis_fits import (
    SAME_START_DEG,
    SAME_START_POSITION,
    EdgeFits,
    Fit,
    left_out,
)
from services.optimizer.mapping import clipped_sides

W, H = 320, 240


@pytest.fixture(scope="module")
def view(catalog):
    """The demo scene's objects, their exact boxes at an oblique rolled camera, that camera's
    intrinsics and world-to-camera ``(rvec, tvec)``."""
    scene = catalog.get("demo")
    objects = scene_objects(scene.spec, scene.assets)
    camera = FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0)
    pinhole = free_pinhole_camera(camera, W, H, objects.fov_deg)
    rotation = np.asarray(pinhole.rotation)
    tvec = np.asarray(pinhole.translation, dtype=np.float64)
    boxes = project_boxes(
        objects, rotation, tvec, (pinhole.fx, pinhole.fy), (pinhole.cx, pinhole.cy)
    )
    rvec = cv2.Rodrigues(rotation)[0].ravel()
    k = Intrinsics(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy)
    return objects, boxes, k, rvec, tvec


@pytest.fixture
def counted(monkeypatch):
    """The number of edge fits made (calls to ``refine_edges``)."""
    calls = []
    real = hypothesis_fits.refine_edges  # type: ignore[attr-defined]

    def refine_edges(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(hypothesis_fits, "refine_edges", refine_edges)
    return calls


def _turned(rvec: np.ndarray, degrees: float) -> np.ndarray:
    """``rvec`` turned a further ``degrees`` about the camera's x axis."""
    rotation = cv2.Rodrigues(rvec)[0]
    extra = cv2.Rodrigues(np.array([np.radians(degrees), 0.0, 0.0]))[0]
    return cv2.Rodrigues(extra @ rotation)[0].ravel()


def test_a_start_already_fitted_shares_its_fit(view, counted):
    objects, boxes, k, rvec, tvec = view
    fits = EdgeFits(objects, boxes, clipped_sides(boxes, W, H))
    pairs = np.arange(len(objects)), np.arange(len(objects))
    first = fits.fit(*pairs, _turned(rvec, 2.0), tvec, k, False)
    again = fits.fit(*pairs, _turned(rvec, 2.0), tvec, k, False)
    assert again is first
    assert len(counted) == 1
    # The fit lands on the true pose (exact boxes), as a fit of its own would.
    assert np.allclose(first.rvec, rvec, atol=1e-5)
    assert np.allclose(first.tvec, tvec, atol=1e-4 * objects.radius)


def test_other_pairs_focal_or_intrinsics_are_fitted_again(view, counted):
    objects, boxes, k, rvec, tvec = view
    fits = EdgeFits(objects, boxes, clipped_sides(boxes, W, H))
    every = np.arange(len(objects))
    fits.fit(every, every, rvec, tvec, k, False)
    fits.fit(every[:-1], every[:-1], rvec, tvec, k, False)
    fits.fit(every, every, rvec, tvec, k, True)
    fits.fit(every, every, rvec, tvec, k.scaled(1.1), False)
    assert len(counted) == 4


def test_a_start_beyond_the_tolerance_is_fitted_again(view, counted, monkeypatch):
    """Centre PnP pulls nearby starts onto one pose, so it is left out here: the starts reach the
    edge fit as given, one within and one beyond :data:`SAME_START_DEG`."""
    objects, boxes, k, rvec, tvec = view
    monkeypatch.setattr(hypothesis_fits, "centre_pnp", lambda _o, _b, _m, r, t, _k: (r, t))
    fits = EdgeFits(objects, boxes, clipped_sides(boxes, W, H))
    every = np.arange(len(objects))
    fits.fit(every, every, rvec, tvec, k, False)
    fits.fit(every, every, _turned(rvec, 0.5 * SAME_START_DEG), tvec, k, False)
    assert len(counted) == 1
    fits.fit(every, every, _turned(rvec, 3.0 * SAME_START_DEG), tvec, k, False)
    assert len(counted) == 2
    shifted = tvec + np.array([3.0 * SAME_START_POSITION * objects.radius, 0.0, 0.0])
    fits.fit(every, every, rvec, shifted, k, False)
    assert len(counted) == 3


def test_a_fitted_focal_stays_within_its_bounds_of_the_reference_whatever_the_start(view):
    """Boxes seen through three times the reference focal length: a fit may not follow them past
    FOCAL_BOUNDS of the reference, not even when it starts from a focal already fitted at the
    bound (as a refit does), where a bound counted from the start would let it step on."""
    objects, _, k, rvec, tvec = view
    zoom = 3.0
    far = tvec * np.array([1.0, 1.0, zoom])  # pulled back along the axis: a dolly zoom
    boxes = project_boxes(
        objects, cv2.Rodrigues(rvec)[0], far, (k.fx * zoom, k.fy * zoom), (k.cx, k.cy)
    )
    fits = EdgeFits(objects, boxes, clipped_sides(boxes, W, H), focal_range=FocalRange.about(k.fx))
    pairs = np.arange(len(objects)), np.arange(len(objects))
    high = FOCAL_BOUNDS[1]
    first = fits.fit(*pairs, rvec, tvec, k, True)
    assert first.intrinsics.fx == pytest.approx(high * k.fx, rel=1e-3)
    again = fits.fit(*pairs, first.rvec, first.tvec, first.intrinsics, True)
    assert again.intrinsics.fx <= high * k.fx * (1 + 1e-6)
    assert at_bound(again.intrinsics.fx, FocalRange.about(k.fx))
    # Counted from its start, the same refit goes on towards the boxes' focal length.
    loose = EdgeFits(objects, boxes, clipped_sides(boxes, W, H))
    assert loose.fit(*pairs, first.rvec, first.tvec, first.intrinsics, True).intrinsics.fx > (
        1.2 * high * k.fx
    )


def test_three_pairs_left_out_keep_the_scene_cameras_focal_length(view):
    """Four objects in view, no intrinsics given, one box 20 px off (its object moved since the
    scene was modelled): the focal length fitted on all four is pulled a third short.
    Refitted without that pair, three pairs are too few to hold a focal length: the refit is
    on the scene camera's, as it says (it once kept the one the moved box had pulled, while
    saying ``scene``)."""
    objects, boxes, k, rvec, tvec = view
    moved = boxes[:4].copy()
    moved[0] += 20.0
    fits = EdgeFits(objects, moved, clipped_sides(moved, W, H), focal_range=FocalRange.about(k.fx))
    pairs = np.arange(4)
    pulled = fits.fit(pairs, pairs, rvec, tvec, k, True)
    assert pulled.intrinsics.fx < 0.9 * k.fx
    compatible = np.eye(4, len(objects), dtype=np.bool_)
    best = Fit(pulled, pairs, pairs, "estimated")
    three = [f for f in left_out(fits, compatible, best, k, (W, H)) if len(f.detections) == 3]
    assert three, "no refit without the moved box"
    for fit in three:
        assert fit.source == "scene"
        assert fit.fit.intrinsics.fx == pytest.approx(k.fx, rel=1e-9)
