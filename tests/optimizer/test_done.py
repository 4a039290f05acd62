"""The done test on photo-like targets: doubtful unpaired detections weigh their confidence,
and the loose tolerance grows with the boxes' expected edge noise, but not enough to accept a
neighbouring grid pose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.common.contracts.optimize import NextPoseRequest
from services.common.geometry.pose import GridIndex
from services.optimizer.calibration import CalibrationStore
from services.optimizer.matching import (
    compare_views,
    without_changed_object,
    without_worst_pair,
)
from services.optimizer.observations import EDGE_NOISE_FRACTION, Observation, box_sizes
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.problem import SearchProblem, Visit
from services.optimizer.strategies.reprojection import plan_reprojection
from simulation import SceneSimulator

RED = (200.0, 30.0, 30.0)


def row(n: int, y: float = 80.0) -> np.ndarray:
    return np.array([[20.0 + 40 * i, y, 50.0 + 40 * i, y + 30] for i in range(n)])


def test_doubtful_unpaired_target_detections_do_not_block_a_match():
    """The zenith-ring failure: 7 pairs at 0.68 px, 2 target boxes at 0.28–0.38 unpaired."""
    view = Observation.from_arrays(["cube"] * 7, row(7), confidence=np.full(7, 0.9))
    doubtful = np.vstack([row(7) + 0.68, row(2, y=180.0)])
    target = Observation.from_arrays(["cube"] * 9, doubtful, confidence=[0.9] * 7 + [0.28, 0.38])
    comparison = compare_views(view, target)
    assert (comparison.unmatched_a, comparison.unmatched_b) == (0, 2)
    assert comparison.unpaired_b == pytest.approx(0.66)
    assert comparison.within(1.0, 1)
    sure = Observation.from_arrays(["cube"] * 9, doubtful, confidence=[0.9] * 9)
    assert not compare_views(view, sure).within(1.0, 1)


def test_the_match_score_falls_with_distance_and_unpaired_confidence():
    view = Observation.from_arrays(["cube"] * 3, row(3))
    same = compare_views(view, Observation.from_arrays(["cube"] * 3, row(3)))
    near = compare_views(view, Observation.from_arrays(["cube"] * 3, row(3) + 1.0))
    far = compare_views(view, Observation.from_arrays(["cube"] * 3, row(3) + 6.0))
    partial = compare_views(view, Observation.from_arrays(["cube"] * 2, row(2)))
    assert same.score(1.0) == 1.0
    assert 1.0 > near.score(1.0) > far.score(1.0) > 0.0
    assert partial.score(1.0) == pytest.approx(0.8)


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    simulator = SceneSimulator.from_scene(scene)
    grid = scene.spec.search.grid()
    return simulator, grid, simulator.grid_views(grid)


def photo(simulator, views, flat: int, rng: np.random.Generator) -> Observation:
    """A JPEG-like target: every edge off by twice the modelled noise of one detection."""
    clean = simulator.clean_observation(views, flat)
    sigma = 2.0 * EDGE_NOISE_FRACTION * box_sizes(clean.boxes)
    boxes = clean.boxes + rng.normal(size=clean.boxes.shape) * sigma[:, np.newaxis]
    return Observation.from_arrays(clean.labels, boxes, clean.colors)


def step(
    simulator,
    grid,
    views,
    target: Observation,
    flats: list[int],
    tolerance: float,
    max_unmatched: int = 1,
):
    history = tuple(
        Visit(
            f,
            float(grid.theta_deg[f]),
            float(grid.phi_deg[f]),
            simulator.clean_observation(views, f),
        )
        for f in flats
    )
    problem = SearchProblem(
        grid, simulator.camera, target, history, tolerance_px=tolerance, max_unmatched=max_unmatched
    )
    return plan_reprojection(problem)


def test_a_noisy_target_passes_at_the_true_pose_and_not_at_a_neighbour(demo):
    simulator, grid, views = demo
    true = grid.flat(GridIndex(lat=4, lon=5))
    tolerance = 0.5  # loose 1.5 px: under the noisier targets' RMS, which must widen it
    clean = simulator.clean_observation(views, true)
    rng = np.random.default_rng(7)
    targets = [photo(simulator, views, true, rng) for _ in range(12)]
    noisy = [t for t in targets if compare_views(clean, t).rms_px > 3 * tolerance]
    assert len(noisy) >= 3  # the old fixed loose tolerance refused these
    for target in noisy:
        plan = step(simulator, grid, views, target, [true], tolerance)
        assert plan.done, plan.reason
        for neighbour in grid.neighbours(grid.unflat(true)).values():
            flat = grid.flat(neighbour)
            for flats in ([flat], [true, flat]):
                plan = step(simulator, grid, views, target, flats, tolerance)
                assert not plan.done, plan.reason


def test_a_target_between_grid_poses_is_found_at_the_nearest_one_that_looks_less_like_it(
    catalog,
):
    """Recorded search (tests/data): the estimate refined at the best-scoring visited view
    (lat 1 lon 9) puts the target nearest the current pose, whose view differs more."""
    recorded = json.loads(
        (Path(__file__).parent / "data" / "garden_offgrid_search.json").read_text()
    )
    del recorded["about"]
    request = NextPoseRequest.model_validate({"scene": "garden", **recorded})
    context = OptimizerContext(calibrations=CalibrationStore.load(), catalog=catalog)
    answer = next_pose(request, context)
    assert answer.done, answer.reason
    assert answer.next.index == GridIndex(lat=2, lon=13)
    assert answer.estimate is not None
    assert abs(answer.estimate.theta_deg - 22.14) < 1.0
    assert abs(answer.estimate.phi_deg - 265.64) < 1.0


@pytest.mark.parametrize(
    ("theta", "sigma", "why"),
    [
        (15.4, None, None),
        (17.5, None, None),
        (18.7, None, "lies almost as near lat 2 lon 0"),
        (17.0, 1.5, None),
        (17.0, 2.0, "lies within 1 σ of the boundary with lat 2 lon 0"),
    ],
)
def test_an_estimate_on_the_edge_between_grid_poses_makes_the_answer_ambiguous(
    demo, theta, sigma, why
):
    """Done by the loose test at lat 1 lon 0 (θ = 15°, φ = 0): an estimate 0.05° short of the
    boundary with lat 2 lon 0 (θ = 22.5°, the boundary at 18.75°) could as well be nearer that
    pose; so could one 1.75° short of it whose σ is 2° (the boundary within one σ), not one
    whose σ is 1.5°."""
    from services.optimizer.problem import Estimate
    from services.optimizer.strategies.done import done_plan

    _, grid, _ = demo
    flat = grid.flat(GridIndex(lat=1, lon=0))
    view = Observation.from_arrays(["sphere"] * 3, row(3))
    target = Observation.from_arrays(["sphere"] * 3, row(3) + 1.5)  # loose, not strict
    current = Visit(flat, 15.0, 0.0, view)
    problem = SearchProblem(grid, demo[0].camera, target, (current,))
    est = Estimate(flat, theta, 0.0, 0.4, 0.9, sigma)
    plan = done_plan(problem, current, compare_views(view, target), est, True)
    assert plan is not None
    assert plan.done
    assert plan.ambiguous == (why is not None), plan.reason
    if why is not None:
        assert [grid.unflat(f) for f, _ in plan.alternatives] == [GridIndex(lat=2, lon=0)]
        assert why in plan.reason


def test_an_estimate_over_two_pairs_makes_the_answer_ambiguous(demo):
    """Done by the loose test at lat 1 lon 0 with an estimate well inside its cell: two pairs
    leave the estimate's error too large to confirm it; three do not."""
    from services.optimizer.problem import Estimate
    from services.optimizer.strategies.done import done_plan

    _, grid, _ = demo
    flat = grid.flat(GridIndex(lat=1, lon=0))
    plans = []
    for n in (2, 3):
        view = Observation.from_arrays(["sphere"] * n, row(n))
        target = Observation.from_arrays(["sphere"] * n, row(n) + 1.5)  # loose, not strict
        current = Visit(flat, 15.0, 0.0, view)
        problem = SearchProblem(grid, demo[0].camera, target, (current,))
        est = Estimate(flat, 15.4, 0.0, 0.4, 0.9)
        plans.append(done_plan(problem, current, compare_views(view, target), est, True))
    two, three = plans
    assert two is not None
    assert three is not None
    assert two.done
    assert three.done
    assert two.ambiguous, two.reason
    assert "only 2 pair(s) support the estimate" in two.reason
    assert len(two.alternatives) == 1
    assert not three.ambiguous, three.reason


def test_three_pairs_that_differ_beyond_their_noise_leave_the_answer_to_a_neighbour_s_view(
    demo,
):
    """Seen with the general model on a generated scene with one object moved: three pairs
    agreed within the loose tolerance only by its slack (RMS 5.8 px, edge noise 2.5 px), the
    estimate 3.8° off and nearer the current pose than the target's, and the answer was
    confirmed a ring off. Views that differ beyond their noise over three pairs leave the
    neighbour the estimate leans to as a check, whose view settles it; over four pairs, or
    within the noise, the estimate stands."""
    from services.optimizer.problem import Estimate
    from services.optimizer.strategies.done import done_plan

    _, grid, _ = demo
    flat = grid.flat(GridIndex(lat=1, lon=0))
    plans = {}
    for n, shift in ((3, 2.5), (4, 2.5), (3, 1.5)):
        view = Observation.from_arrays(["sphere"] * n, row(n))
        target = Observation.from_arrays(["sphere"] * n, row(n) + shift)
        comparison = compare_views(view, target)
        assert comparison.rms_px > 1.0  # not strict: done by the loose test
        current = Visit(flat, 15.0, 0.0, view)
        problem = SearchProblem(grid, demo[0].camera, target, (current,))
        est = Estimate(flat, 16.2, 0.0, 0.4, 0.9, 0.5)  # well inside its cell, σ small
        plans[n, shift] = done_plan(problem, current, comparison, est, True)
    strained = plans[3, 2.5]
    assert strained is not None
    assert strained.done
    assert strained.ambiguous, strained.reason
    assert "differ by more than their edge noise, and 3 pairs alone" in strained.reason
    assert strained.checks == (grid.flat(GridIndex(lat=2, lon=0)),)
    for other in (plans[4, 2.5], plans[3, 1.5]):
        assert other is not None
        assert other.done
        assert not other.ambiguous, other.reason


def test_one_pair_far_off_is_left_unpaired_when_its_confidence_allows():
    """Seen on a generated scene: a partly visible object boxed as a cone in the view and a cube
    in the target, 15 px apart, while the other pairs agree to a pixel."""
    boxes = row(5)
    view = Observation.from_arrays(["cube"] * 5, boxes, confidence=[0.9] * 4 + [0.39])
    moved = boxes.copy()
    moved[4] += [5.0, -5.0, 29.0, -2.0]
    target = Observation.from_arrays(["cube"] * 5, moved, confidence=[0.9] * 4 + [0.26])
    full = compare_views(view, target)
    assert len(full.pairs) == 5
    assert not full.within(1.0, 1)
    trimmed = without_worst_pair(view, target, full, 1)
    assert trimmed is not None
    assert len(trimmed.pairs) == 4
    assert trimmed.rms_px == pytest.approx(0.0)
    assert (trimmed.unpaired_a, trimmed.unpaired_b) == pytest.approx((0.39, 0.26))
    assert trimmed.within(1.0, 1)
    # A sure detection is not dropped, nor a pair that would leave fewer than three.
    sure = Observation.from_arrays(["cube"] * 5, moved, confidence=[0.9] * 5)
    assert without_worst_pair(view, sure, compare_views(view, sure), 0.5) is None
    three = Observation.from_arrays(["cube"] * 3, boxes[2:], confidence=[0.9, 0.9, 0.39])
    assert without_worst_pair(three, target, compare_views(three, target), 1) is None


def test_a_moved_object_does_not_hold_up_the_true_pose_but_a_neighbour_still_fails(demo):
    simulator, grid, views = demo
    true = grid.flat(GridIndex(lat=4, lon=5))
    clean = simulator.clean_observation(views, true)
    boxes = clean.boxes.copy()
    boxes[0] += 12.0  # one object moved since the scene file (the bench's ``changed`` target)
    target = Observation.from_arrays(
        clean.labels, boxes, clean.colors, confidence=[0.9] * len(clean)
    )
    plan = step(simulator, grid, views, target, [true], 1.0)
    assert plan.done, plan.reason
    for neighbour in grid.neighbours(grid.unflat(true)).values():
        plan = step(simulator, grid, views, target, [grid.flat(neighbour)], 1.0)
        assert not (plan.done and plan.next_flat != true), plan.reason


GREEN = (30.0, 200.0, 30.0)
BLUE = (30.0, 30.0, 200.0)


def test_one_object_gone_moved_far_or_come_is_left_out_of_the_unpaired_allowance():
    """A site changes: a sure detection without a partner (the object gone from the photo, or
    new in it), or one in each image alike in colour (moved beyond the pairing gate), no longer
    holds up four pairs that agree; two such objects, or unlike ones, still do."""
    boxes = row(5)
    colours = [RED] * 4 + [GREEN]
    view = Observation.from_arrays(["cube"] * 5, boxes, colours, confidence=[0.9] * 5)
    gone = Observation.from_arrays(["cube"] * 4, boxes[:4], [RED] * 4, confidence=[0.9] * 4)
    full = compare_views(view, gone)
    assert not full.within(1.0, 0.5)
    excused = without_changed_object(view, gone, full)
    assert excused is not None
    assert excused.within(1.0, 0.5)
    assert (excused.unmatched_a, excused.unmatched_b) == (0, 0)
    assert "not in the target" in excused.changed
    # Moved beyond the gate: one unpaired in each image, alike.
    far = boxes.copy()
    far[4] += [0.0, 90.0, 0.0, 90.0]
    moved = Observation.from_arrays(["cube"] * 5, far, colours, confidence=[0.9] * 5)
    full = compare_views(view, moved)
    assert (full.unmatched_a, full.unmatched_b) == (1, 1)
    excused = without_changed_object(view, moved, full)
    assert excused is not None
    assert excused.within(1.0, 0.5)
    assert "moved" in excused.changed
    # Unlike colours are two objects, not one moved: one of them still weighs.
    other = Observation.from_arrays(["cube"] * 5, far, [RED] * 4 + [BLUE], confidence=[0.9] * 5)
    excused = without_changed_object(view, other, compare_views(view, other))
    assert excused is not None
    assert not excused.within(1.0, 0.5)
    # Two objects gone: one is left out, the other still weighs.
    two_gone = Observation.from_arrays(["cube"] * 3, boxes[:3], [RED] * 3, confidence=[0.9] * 3)
    excused = without_changed_object(view, two_gone, compare_views(view, two_gone))
    assert excused is not None
    assert not excused.within(1.0, 0.5)
    # Fewer than three pairs never pin a pose.
    pair = Observation.from_arrays(["cube"] * 2, boxes[:2], [RED] * 2, confidence=[0.9] * 2)
    three = Observation.from_arrays(["cube"] * 3, boxes[:3], [RED] * 2 + [GREEN])
    assert without_changed_object(three, pair, compare_views(three, pair)) is None


@pytest.mark.parametrize("change", ["gone", "moved far"])
def test_an_object_gone_or_moved_far_does_not_hold_up_the_true_pose(demo, change):
    """The bench's ``changed`` targets whose object left the site or moved beyond the pairing
    gate: the true pose is done at its first view (before, such searches wandered for 14-25
    renders and ended unconfirmed at that view); no neighbour is taken for it."""
    simulator, grid, views = demo
    true = grid.flat(GridIndex(lat=4, lon=5))
    clean = simulator.clean_observation(views, true)
    keep = np.arange(len(clean))
    boxes = clean.boxes.copy()
    if change == "gone":
        keep = keep[1:]
    else:
        boxes[0] += [70.0, 40.0, 70.0, 40.0]
    target = Observation.from_arrays(
        [clean.labels[i] for i in keep], boxes[keep], clean.colors[keep],
        confidence=[0.9] * len(keep),
    )  # fmt: skip
    # An allowance below one sure detection: the changed object alone would hold the view up.
    plan = step(simulator, grid, views, target, [true], 1.0, max_unmatched=0)
    assert plan.done, plan.reason
    assert plan.next_flat == true
    assert "since the scene file" in plan.reason
    for neighbour in grid.neighbours(grid.unflat(true)).values():
        plan = step(simulator, grid, views, target, [grid.flat(neighbour)], 1.0, max_unmatched=0)
        assert not (plan.done and plan.next_flat != true), plan.reason


@pytest.fixture(scope="module")
def loose_at_true(demo):
    """A noisy target of lat 4 lon 5 that the view there matches loosely, not strictly; the
    problem at that view and the map fused from it."""
    from services.optimizer.strategies.map_based import map_estimate, map_views

    simulator, grid, views = demo
    true = grid.flat(GridIndex(lat=4, lon=5))
    tolerance = 0.5  # loose, not strict, for these targets (as above)
    clean = simulator.clean_observation(views, true)
    rng = np.random.default_rng(7)
    targets = [photo(simulator, views, true, rng) for _ in range(12)]
    target = next(t for t in targets if compare_views(clean, t).rms_px > 3 * tolerance)
    current = Visit(true, float(grid.theta_deg[true]), float(grid.phi_deg[true]), clean)
    problem = SearchProblem(grid, simulator.camera, target, (current,), tolerance_px=tolerance)
    found = map_estimate(problem, map_views(problem.history, grid, problem.camera, None))
    assert found is not None
    assert found.best == true
    return problem, current, found


def test_an_answer_whose_estimate_was_not_refined_is_ambiguous_with_its_best_neighbour(
    loose_at_true,
):
    """Done by the loose test on an estimate that is only its grid pose's score (no view
    anchors the map there): it cannot rule out a neighbour. The refined one, from the same map
    anchored by the view, can."""
    from dataclasses import replace

    from services.optimizer.strategies.done import done_plan
    from services.optimizer.strategies.map_based import plan_estimate

    problem, current, found = loose_at_true
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    est, refined, rival = plan_estimate(problem, current, found)
    assert refined is not None
    assert rival is None
    anchored = done_plan(problem, current, comparison, est, True, refined, rival=rival)
    assert anchored is not None
    assert anchored.done
    assert not anchored.ambiguous, anchored.reason

    est, refined, rival = plan_estimate(problem, current, replace(found, anchors=()))
    assert refined is None
    assert rival is not None
    assert (est.theta_deg, est.phi_deg) == (
        grid.theta_deg[current.flat],
        grid.phi_deg[current.flat],
    )
    neighbours = [grid.flat(n) for n in grid.neighbours(grid.unflat(current.flat)).values()]
    assert rival.flat == min(neighbours, key=lambda f: found.scores.coarse[f])
    plan = done_plan(problem, current, comparison, est, True, refined, rival=rival)
    assert plan is not None
    assert plan.done
    assert plan.ambiguous, plan.reason
    assert plan.alternatives == ((rival.flat, rival.score),)
    other = grid.unflat(rival.flat)
    assert "not refined between grid poses" in plan.reason
    assert f"cannot tell this grid pose from lat {other.lat} lon {other.lon}" in plan.reason


def test_an_answer_kept_over_a_robust_fit_nearer_another_grid_pose_is_ambiguous(
    loose_at_true, monkeypatch
):
    """Seen with the general model on a generated scene (seed 7, offgrid, θ 61.5° on an 8°
    grid): the robust refinement went to θ 60.4° (nearest the true ring) but its RMS, raised by
    one object boxed twice, lost to the start's, the grid pose one ring up, and the answer was
    confirmed there. A fit kept at the start that stays nearest it is no rival."""
    import services.optimizer.strategies.map_based as map_based
    from services.optimizer.reprojection import Refinement
    from services.optimizer.strategies.done import done_plan

    problem, current, found = loose_at_true
    grid = problem.grid
    comparison = compare_views(current.observation, problem.target)
    south = grid.flat(grid.neighbours(grid.unflat(current.flat))["S"])
    plans = {}
    for name, fit in (
        ("near", (current.theta_deg + 0.2, current.phi_deg)),
        ("far", (float(grid.theta_deg[south]) - 0.3, float(grid.phi_deg[south]))),
    ):
        kept = Refinement(current.theta_deg, current.phi_deg, 2.0, 5, fit)
        assert kept.kept_start
        monkeypatch.setattr(map_based, "refine_pose", lambda *_, kept=kept, **__: kept)
        est, refined, rival = map_based.plan_estimate(problem, current, found)
        assert refined is not None
        plans[name] = done_plan(problem, current, comparison, est, True, refined, rival=rival)
    near, far = plans["near"], plans["far"]
    assert near is not None
    assert far is not None
    assert near.done
    assert far.done
    assert not near.ambiguous, near.reason
    assert far.ambiguous, far.reason
    assert [f for f, _ in far.alternatives] == [south]
    assert "the robust refinement puts the target at" in far.reason


def test_the_refined_estimate_is_less_certain_near_the_zenith(demo):
    """The same box noise pins θ less near the zenith, where a step of θ moves the objects
    little: the refinement's σ at lat 1 (θ = 15°) is larger than at lat 5 (θ = 45°)."""
    from services.optimizer.strategies.map_based import map_estimate, map_views, plan_estimate

    simulator, grid, views = demo
    sigmas = {}
    for lat in (1, 5):
        flat = grid.flat(GridIndex(lat=lat, lon=2))
        clean = simulator.clean_observation(views, flat)
        rng = np.random.default_rng(3)
        values = []
        for _ in range(6):
            target = photo(simulator, views, flat, rng)
            current = Visit(flat, float(grid.theta_deg[flat]), float(grid.phi_deg[flat]), clean)
            problem = SearchProblem(grid, simulator.camera, target, (current,))
            found = map_estimate(problem, map_views(problem.history, grid, problem.camera, None))
            assert found is not None
            est, _, _ = plan_estimate(problem, current, found)
            assert est.sigma_deg is not None
            assert 0.0 < est.sigma_deg < 5.0
            values.append(est.sigma_deg)
        sigmas[lat] = float(np.median(values))
    assert sigmas[1] > 1.5 * sigmas[5], sigmas
