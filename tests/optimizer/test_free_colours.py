"""Labels checked against the colours the detector measured: a changed scene's mislabelled
object is paired by its colour, and a general-model pairing pays for its colour distance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.common.contracts.detect import Detection
from services.common.geometry.free_camera import FreeCamera, free_pinhole_camera
from services.optimizer.free import scene_objects, solve_free_pose
from services.optimizer.free.colours import (
    AGREES,
    COLOUR_COST,
    CONTRADICTED,
    RELABEL_COST,
    TONE_GAMMA,
    colour_distances,
    recoloured,
)
from services.optimizer.free.hypotheses import SHAPE_MISMATCH_COST, general_labels, label_costs
from tests.optimizer.test_free_pose import H, W, errors, exact_detections, intrinsics_of


def shaded_srgb(linear: np.ndarray, shade: float, gamma: float = 1.0) -> tuple[float, float, float]:
    """The sRGB (0–255) of a linear-RGB reflectance lit by a white light at ``shade``, through
    a tone curve that takes linear values to the power ``gamma``."""
    c = np.clip(np.asarray(linear) * shade, 0.0, 1.0) ** gamma
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    r, g, b = (float(v) for v in 255.0 * srgb)
    return r, g, b


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    return scene_objects(scene.spec, scene.assets)


@pytest.fixture(scope="module")
def garden(catalog):
    scene = catalog.get("garden")
    return scene_objects(scene.spec, scene.assets)


def drone_view(objects, seen, truth: FreeCamera, *, given: bool = True):
    """The box solve of detections ``seen`` (label, box, measured colour each) of a view from
    ``truth``, its intrinsics given or not: the answer, its position and rotation errors."""
    detections = [
        Detection(label=label, class_id=i, confidence=0.85, box=box, color=color)
        for i, (label, box, color) in enumerate(seen)
    ]
    pinhole = free_pinhole_camera(truth, W, H, truth.fov_deg)
    k = intrinsics_of(pinhole) if given else None
    answer = solve_free_pose(objects, detections, W, H, k)
    return answer, *errors(answer.pose, pinhole)


def test_a_colour_is_near_its_object_under_any_shade_and_far_from_the_others(demo):
    names = list(demo.names)
    for shade in (0.3, 0.6, 1.0):
        measured = [shaded_srgb(c, shade) for c in demo.colors]
        d = colour_distances(measured, demo)
        assert np.all(np.diag(d) < 0.01)
        off = d[~np.eye(len(names), dtype=bool)]
        assert np.all(off > 2 * CONTRADICTED)


def test_a_colour_through_another_tone_curve_is_still_near_its_object(demo):
    """A photo's tone curve is not sRGB's: a power on the linear values changes a colour's
    chromaticity (the demo's balls by up to 0.05 at 1.2), not the object it is nearest."""
    names = list(demo.names)
    for gamma in (1.0 / TONE_GAMMA, TONE_GAMMA):
        measured = [shaded_srgb(c, 0.7, gamma) for c in demo.colors]
        d = colour_distances(measured, demo)
        assert np.all(np.diag(d) < 0.01)
        off = d[~np.eye(len(names), dtype=bool)]
        assert np.all(off > CONTRADICTED)


def test_a_photo_s_tone_curve_does_not_hide_a_mislabelled_object(garden):
    """The garden's own model on a drone photo (the free bench's seed 41, target 2, ``photo``:
    exposure and a gamma of 0.8-1.25): it named the red ball ``duck`` and the green post
    ``arch``. Their colours, 0.06-0.07 from their objects' until the tone curve is allowed
    for, still name them."""
    labels = ("duck", "arch")
    measured = [(160.3, 45.6, 44.9), (41.0, 136.7, 61.3)]
    out = recoloured(label_costs(garden, labels), garden, general_labels(garden, labels), measured)
    assert out[0, garden.names.index("red")] == RELABEL_COST + SHAPE_MISMATCH_COST
    assert out[1, garden.names.index("post")] == RELABEL_COST + SHAPE_MISMATCH_COST
    assert out[0, garden.names.index("duck")] == 0.0
    assert out[1, garden.names.index("arch")] == 0.0


def test_dark_unknown_and_textured_colours_are_not_compared(demo):
    colors = demo.colors.copy()
    colors[0] = np.nan  # an object of unknown colour
    textured = dataclasses.replace(demo, colors=colors)
    d = colour_distances([(20.0, 10.0, 10.0), (np.nan,) * 3, (200.0, 30.0, 30.0)], textured)
    assert np.isnan(d[0]).all()
    assert np.isnan(d[1]).all()
    assert np.isnan(d[2, 0])
    assert np.isfinite(d[2, 1:]).all()


def test_a_label_its_colour_contradicts_may_also_be_the_object_of_that_colour(demo):
    red, magenta = demo.names.index("red"), demo.names.index("magenta")
    labels = ("red", "red", "blue")
    costs = label_costs(demo, labels)
    measured = [
        shaded_srgb(demo.colors[magenta], 0.7),  # the magenta ball, named red
        shaded_srgb(demo.colors[red], 0.7),  # the red ball, named right
        (20.0, 20.0, 30.0),  # too dark to say anything
    ]
    out = recoloured(costs, demo, general_labels(demo, labels), measured)
    assert out[0, red] == 0.0
    assert out[0, magenta] == RELABEL_COST
    assert np.isinf(np.delete(out[0], [red, magenta])).all()
    np.testing.assert_array_equal(out[1:], costs[1:])


def test_a_general_model_pairing_is_priced_by_its_colour(demo):
    """The demo's balls are all spheres: by shape, a ``sphere`` detection is any of them alike.
    Its colour makes its own ball free, a far colour dear, and a ``cube`` label on that ball
    costs nothing more than its colour says (the general model's shapes are often wrong)."""
    labels = ("sphere", "cube", "sphere")
    costs = label_costs(demo, labels)
    assert np.all(costs[0] == 0.0)
    assert np.all(costs[1] == SHAPE_MISMATCH_COST)
    measured = [
        shaded_srgb(demo.colors[0], 0.8),
        shaded_srgb(demo.colors[0], 0.5),
        (20.0, 20.0, 30.0),  # too dark to say anything
    ]
    d = colour_distances(measured, demo)
    out = recoloured(costs, demo, general_labels(demo, labels), measured)
    assert out[0, 0] < 0.05
    assert out[1, 0] < 0.05
    far = d[0] >= CONTRADICTED
    assert far[1:].all()
    np.testing.assert_allclose(out[0, far], COLOUR_COST)
    np.testing.assert_allclose(out[1, far], SHAPE_MISMATCH_COST + COLOUR_COST)
    np.testing.assert_array_equal(out[2], costs[2])
    assert np.isfinite(out).all()  # evidence, not proof: every pairing stays possible
    assert AGREES < CONTRADICTED


def test_a_drone_view_whose_shapes_the_scene_model_mistook(garden):
    """The garden's own model on a held-out drone view (the free bench's seed 27, target 1,
    JPEG): it named the red ball, cut by the border, ``duck`` and the green post ``arch``.
    Their colours name them; with the post paired by its colour the pose is found (allowed only
    objects of the label's shape, the answer was 1.1 radii off)."""
    seen = [
        ("duck", (76.89, 0.0, 108.59, 14.67), (148.8, 53.5, 53.7)),
        ("duck", (195.4, 8.0, 224.46, 37.18), (141.8, 112.5, 19.5)),
        ("crate", (98.97, 64.58, 139.72, 105.37), (149.2, 113.0, 72.6)),
        ("arch", (9.06, 49.92, 47.67, 89.98), (63.6, 161.2, 85.3)),
        ("hat", (6.39, 9.34, 35.77, 43.44), (187.6, 148.7, 72.6)),
    ]
    truth = FreeCamera(
        position=(-6.4411, 3.2002, 6.8369),
        quaternion_wxyz=(0.1818, -0.3226, 0.9041, -0.2131),
        fov_deg=44.6991,
    )
    answer, moved, turned = drone_view(garden, seen, truth)
    assert moved < 0.05 * garden.radius, answer.reason
    assert turned < 2.0, answer.reason
    assert any(c.label == "arch" and c.object == "post" for c in answer.pose.correspondences)


def test_a_textured_object_has_its_texture_s_colour(garden):
    """The garden's duck is textured: its colour is its texture's, so a label naming it can be
    contradicted. On a held-out drone view (the free bench's seed 27, target 5, its fov not
    given) the garden's model named the red ball, cut by the border, ``duck`` and the orange hat
    ``red``: by their colours both are paired right (the duck of unknown colour, the answer was
    37 % of the radius and 50° off)."""
    assert np.isfinite(garden.colors).all()
    seen = [
        ("post", (171.13, 83.28, 211.63, 140.49), (77.8, 199.6, 107.4)),
        ("crate", (265.12, 14.97, 319.62, 76.34), (159.5, 120.8, 78.9)),
        ("duck", (107.62, 0.0, 147.72, 13.85), (196.7, 69.9, 68.4)),
        ("red", (49.38, 73.25, 93.81, 118.15), (217.8, 170.9, 76.3)),
    ]
    truth = FreeCamera(
        position=(2.2009, 5.6298, 7.8701),
        quaternion_wxyz=(0.0545, -0.0921, -0.9679, 0.2276),
        fov_deg=31.7327,
    )
    answer, moved, turned = drone_view(garden, seen, truth, given=False)
    assert moved < 0.05 * garden.radius, answer.reason
    assert turned < 2.0, answer.reason
    paired = {(c.label, c.object) for c in answer.pose.correspondences}
    assert {("duck", "red"), ("red", "hat")} <= paired


VIEWS = [
    FreeCamera(position=(5.0, -4.0, 5.0), look_at=(0.0, 0.0, 0.0)),
    FreeCamera(position=(-6.0, 2.0, 4.0), look_at=(0.5, 0.0, 0.0), roll_deg=20.0),
    FreeCamera(position=(2.0, 7.0, 3.5), look_at=(-0.5, 0.5, 0.0), roll_deg=-10.0),
    FreeCamera(position=(7.0, 3.0, 3.0), look_at=(0.0, 0.0, 0.3)),
]


@pytest.mark.parametrize("view", range(len(VIEWS)))
def test_the_red_ball_left_out_and_the_magenta_one_named_red(demo, view):
    """What the demo's own model did on a photo without the red ball (the free bench, seed 1,
    changed #5): it named the magenta ball ``red``. By its label alone the solve pairs it with
    the red ball's place; by its colour it is the magenta ball, and the pose is exact."""
    pinhole = free_pinhole_camera(VIEWS[view], W, H, demo.fov_deg)
    rng = np.random.default_rng(view)
    red, magenta = demo.names.index("red"), demo.names.index("magenta")
    shown = [i for i in range(len(demo)) if i != red]
    detections = exact_detections(demo.subset(shown), pinhole, 0.3, rng)
    assert len(detections) == 4
    coloured = [
        d.model_copy(
            update={
                "label": "red" if d.label == "magenta" else d.label,
                "color": shaded_srgb(demo.colors[demo.labels.index(d.label)], 0.7),
            }
        )
        for d in detections
    ]
    assert any(d.label == "red" and d.color is not None for d in coloured)
    k = intrinsics_of(pinhole)
    answer = solve_free_pose(demo, coloured, W, H, k)
    moved, turned = errors(answer.pose, pinhole)
    assert moved < 0.02 * demo.radius, answer.reason
    assert turned < 1.0, answer.reason
    assert {c.object for c in answer.pose.correspondences} == {demo.names[i] for i in shown}
    assert any(c.label == "red" and c.object == "magenta" for c in answer.pose.correspondences)
    blind = [d.model_copy(update={"color": None}) for d in coloured]
    by_label = solve_free_pose(demo, blind, W, H, k)
    assert magenta not in {demo.names.index(c.object) for c in by_label.pose.correspondences}
    assert by_label.pose.inliers < answer.pose.inliers


def test_a_label_its_colour_contradicts_may_be_an_object_of_another_shape(garden):
    """The garden's own model named its green post (a cylinder) ``arch`` (a blue mesh) on a
    drone view: the post may be paired too, a wrong shape dearer. The arch stays compatible."""
    post, arch = garden.names.index("post"), garden.names.index("arch")
    assert garden.shapes[post] != garden.shapes[arch]
    labels = ("arch",)
    costs = label_costs(garden, labels)
    measured = [shaded_srgb(garden.colors[post], 0.6)]
    out = recoloured(costs, garden, general_labels(garden, labels), measured)
    assert out[0, arch] == 0.0
    assert out[0, post] == RELABEL_COST + SHAPE_MISMATCH_COST
    assert np.isinf(np.delete(out[0], [post, arch])).all()


def test_a_mislabel_the_colour_allows_and_a_spurious_box_leave_the_right_triple(garden):
    """The garden's own model on a held-out view (the free bench's seed 27, target 7): the
    duck named ``crate`` (its colour does not say otherwise) and a spurious ``hat`` in the
    corner. Only three boxes pair, so a dozen triples fit their centres exactly at the same
    cost; their boxes' extents now rank the right one first among them (taken in the solver's
    order it came last, and the answer was 1.1 radii off)."""
    seen = [
        ("red", (102.9, 75.9, 149.4, 122.4), (151.5, 52.1, 51.3)),
        ("arch", (221.1, 78.9, 275.0, 127.2), (71.2, 86.2, 142.7)),
        ("hat", (37.6, 78.5, 70.0, 119.7), (176.6, 136.5, 59.4)),
        ("hat", (0.0, 174.6, 42.7, 240.0), (113.1, 84.2, 53.1)),
        ("crate", (170.8, 175.5, 236.4, 226.1), (133.0, 105.5, 13.8)),
    ]
    truth = FreeCamera(
        position=(-6.1761, -1.7612, 3.4698),
        quaternion_wxyz=(0.4375, -0.5472, 0.6514, -0.2913),
        fov_deg=38.7046,
    )
    answer, moved, turned = drone_view(garden, seen, truth)
    assert moved < 0.05 * garden.radius, answer.reason
    assert turned < 2.0, answer.reason
    pairs = {(c.label, c.object) for c in answer.pose.correspondences}
    assert {("red", "red"), ("arch", "arch"), ("hat", "hat")} <= pairs
