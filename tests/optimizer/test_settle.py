"""An ambiguous answer settled by rendering its checks: a check not seen yet is rendered, a
check whose view matches the target keeps the answer ambiguous, and only checks ruled out by
their views leave it standing alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from services.common.geometry.pose import GridIndex
from services.optimizer.matching import compare_views
from services.optimizer.observations import Observation
from services.optimizer.problem import Estimate, Plan, SearchProblem, Visit
from services.optimizer.strategies.done import done_plan
from services.optimizer.strategies.settle import (
    MAX_CHECKS,
    Settling,
    next_check,
    settle,
    settling,
)
from simulation import SceneSimulator


def row(n: int) -> np.ndarray:
    return np.array([[20.0 + 40 * i, 80.0, 50.0 + 40 * i, 110.0] for i in range(n)])


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    simulator = SceneSimulator.from_scene(scene)
    return simulator.camera, scene.spec.search.grid()


VIEW = Observation.from_arrays(["sphere"] * 3, row(3))
TARGET = Observation.from_arrays(["sphere"] * 3, row(3) + 1.5)  # loose, not strict at 0.5 px


def _problem(demo, *visits: Visit, tolerance: float = 0.5) -> SearchProblem:
    camera, grid = demo
    return SearchProblem(grid, camera, TARGET, visits, tolerance_px=tolerance)


def _answer(demo) -> Visit:
    flat = demo[1].flat(GridIndex(lat=1, lon=0))
    return Visit(flat, 15.0, 0.0, VIEW)


def _check(demo, observation: Observation) -> Visit:
    flat = demo[1].flat(GridIndex(lat=2, lon=0))
    return Visit(flat, 22.5, 0.0, observation)


def _edge_plan(problem: SearchProblem) -> Plan | None:
    """Done by the loose test at the current pose with an estimate 0.05° short of the boundary
    with lat 2 lon 0 (θ = 18.75°): ambiguous, that pose its one check, unless the current
    pose is that check."""
    current = problem.current
    assert current is not None
    est = Estimate(problem.grid.flat(GridIndex(lat=1, lon=0)), 18.7, 0.0, 0.4, 0.9)
    comparison = compare_views(current.observation, problem.target)
    return done_plan(problem, current, comparison, est, est.flat == current.flat)


def test_an_answer_on_the_edge_renders_its_neighbour_before_it_ends(demo):
    problem = _problem(demo, _answer(demo))
    plan = _edge_plan(problem)
    assert plan is not None
    assert plan.done
    assert plan.ambiguous
    assert plan.checks == (demo[1].flat(GridIndex(lat=2, lon=0)),)
    moved = settle(problem, plan)
    assert not moved.done
    assert moved.next_flat == plan.checks[0]
    assert "rendering lat 2 lon 0 to settle it" in moved.reason


def test_a_check_whose_view_is_far_off_leaves_the_answer_standing(demo):
    far = Observation.from_arrays(["sphere"] * 3, row(3) + 12.0)
    problem = _problem(demo, _answer(demo), _check(demo, far), _answer(demo))
    plan = _edge_plan(problem)
    assert plan is not None
    settled = settle(problem, plan)
    assert settled.done
    assert not settled.ambiguous, settled.reason
    assert settled.alternatives == ()
    assert "settled by rendering: the view of lat 2 lon 0 (RMS 10.50 px)" in settled.reason
    assert "ambiguous:" not in settled.reason


@pytest.mark.parametrize(
    ("shift", "tolerance", "why"),
    [
        (1.5, 0.5, "the view of lat 2 lon 0 (RMS 0.00 px) matches the target too"),  # the target
        (2.0, 0.5, "the view of lat 2 lon 0 (RMS 0.50 px) matches the target too"),  # nearer
        # worse than the answer's view by more than its noise (0.94 px), but within the loose
        # tolerance (3.54 px)
        (4.3, 1.0, "the view of lat 2 lon 0 (RMS 2.80 px) matches the target too"),
    ],
)
def test_a_check_whose_view_matches_keeps_the_answer_ambiguous(demo, shift, tolerance, why):
    near = Observation.from_arrays(["sphere"] * 3, row(3) + shift)
    visits = (_answer(demo), _check(demo, near), _answer(demo))
    problem = _problem(demo, *visits, tolerance=tolerance)
    plan = _edge_plan(problem)
    assert plan is not None
    kept = settle(problem, plan)
    assert kept.done
    assert kept.ambiguous
    assert kept.alternatives == plan.alternatives
    assert why in kept.reason


def test_a_check_worse_only_within_its_noise_keeps_the_answer_ambiguous(demo):
    """A check that fails the loose test, yet matches the target barely worse than the answer
    (big boxes, large edge noise), does not settle it."""
    big = np.array([[10.0 + 90 * i, 40.0, 90.0 + 90 * i, 200.0] for i in range(3)])
    target = Observation.from_arrays(["sphere"] * 3, big + 6.0)
    answer = Visit(demo[1].flat(GridIndex(lat=1, lon=0)), 15.0, 0.0, Observation.from_arrays(
        ["sphere"] * 3, big
    ))  # fmt: skip
    check = _check(demo, Observation.from_arrays(["sphere"] * 3, big + 13.0))
    camera, grid = demo
    problem = SearchProblem(grid, camera, target, (answer, check, answer), tolerance_px=0.5)
    whole = compare_views(check.observation, target)
    loose = whole.tolerance(1.5, 2.0)
    own = compare_views(answer.observation, target).rms_px
    assert whole.rms_px > loose  # fails the loose test ...
    assert whole.rms_px <= own + whole.noise_px  # ... but not by more than its noise
    plan = _edge_plan(problem)
    assert plan is not None
    assert plan.ambiguous
    assert settle(problem, plan).ambiguous


def test_answers_no_view_can_settle_are_left_as_they_are(demo):
    """Two pairs (the estimate's error reaches farther than a neighbour), and more checks than
    :data:`MAX_CHECKS`."""
    two = Observation.from_arrays(["sphere"] * 2, row(2))
    camera, grid = demo
    current = Visit(grid.flat(GridIndex(lat=1, lon=0)), 15.0, 0.0, two)
    target = Observation.from_arrays(["sphere"] * 2, row(2) + 1.5)
    problem = SearchProblem(grid, camera, target, (current,), tolerance_px=0.5)
    est = Estimate(current.flat, 15.4, 0.0, 0.4, 0.9)
    plan = done_plan(problem, current, compare_views(two, target), est, True)
    assert plan is not None
    assert plan.ambiguous
    assert plan.checks is None
    assert settle(problem, plan) is plan
    many = tuple(range(current.flat + 1, current.flat + 2 + MAX_CHECKS))
    crowded = Plan(True, current.flat, "stay", est, True, (), "ambiguous", many)
    assert settle(problem, crowded) is crowded


def _settling(demo, *visits: Visit) -> Settling | None:
    problem = _problem(demo, *visits)
    return settling(problem, lambda history: _edge_plan(replace(problem, history=history)))


def test_the_last_check_that_is_not_done_goes_back_to_the_answer(demo):
    far = Observation.from_arrays(["sphere"] * 3, row(3) + 12.0)
    answer, check = _answer(demo), _check(demo, far)
    pending = _settling(demo, answer, check)
    assert pending is not None
    assert pending.answer is answer
    back = next_check(_problem(demo, answer, check), pending)
    assert not back.done
    assert back.next_flat == answer.flat
    assert back.move == "N"
    assert "rendered to settle the answer at lat 1 lon 0" in back.reason
    # back there, the answer is still the one being settled, on its first plan
    again = _settling(demo, answer, check, answer)
    assert again is not None
    assert again.answer is answer
    assert again.plan == pending.plan


def test_checks_are_rendered_in_a_row_and_the_answer_seen_twice(demo):
    """Three checks: each view not done goes on to the next, the last back to the answer,
    which their views then leave standing alone. The answer is seen twice: a return after each
    check would have seen it four times, and the optimizer calls a pose seen three times
    stuck."""
    camera, grid = demo
    far = Observation.from_arrays(["sphere"] * 3, row(3) + 12.0)
    answer = _answer(demo)
    flats = tuple(grid.flat(GridIndex(lat=2, lon=k)) for k in (0, 1, 2))
    checks = [Visit(f, 22.5, 45.0 * k, far) for k, f in enumerate(flats)]
    est = Estimate(answer.flat, 15.0, 0.0, 0.4, 0.9)
    plan = Plan(True, answer.flat, "stay", est, True, (), "ambiguous", flats)

    def plan_at(history: tuple[Visit, ...]) -> Plan | None:
        return plan if history[-1] is answer else None

    first = settle(_problem(demo, answer), plan)
    assert not first.done
    assert first.next_flat == flats[0]
    for i in range(3):
        problem = _problem(demo, answer, *checks[: i + 1])
        pending = settling(problem, plan_at)
        assert pending is not None
        assert pending.answer is answer
        step = next_check(problem, pending)
        assert step.next_flat == (flats[i + 1] if i < 2 else answer.flat)
        assert ("on to lat 2" if i < 2 else "back there") in step.reason
    problem = _problem(demo, answer, *checks, answer)
    pending = settling(problem, plan_at)
    assert pending is not None
    settled = settle(problem, pending.plan)
    assert settled.done
    assert not settled.ambiguous
    assert "settled by rendering" in settled.reason
    # a check seen twice is no settling of this kind
    assert settling(_problem(demo, answer, checks[0], checks[0]), plan_at) is None


def test_only_checks_of_an_answer_its_view_vouches_for_are_being_settled(demo):
    far = Observation.from_arrays(["sphere"] * 3, row(3) + 12.0)
    answer, check = _answer(demo), _check(demo, far)
    other = Visit(demo[1].flat(GridIndex(lat=1, lon=1)), 15.0, 45.0, far)
    assert _settling(demo, answer, other) is None  # no check of the answer
    assert _settling(demo, check) is None  # a first view
    assert _settling(demo, answer, check, other) is None  # gone elsewhere since
    unsure = replace(answer, observation=Observation.from_arrays(["sphere"] * 3, row(3) + 9.0))
    assert _settling(demo, unsure, check) is None  # its own view fails the loose test


def test_an_answer_whose_own_view_fails_the_loose_test_is_not_settled(demo):
    """Done on the map's prediction between grid poses, not on its view: a check's view worse
    than that one's cannot vouch for it."""
    unsure = replace(
        _answer(demo), observation=Observation.from_arrays(["sphere"] * 3, row(3) + 9.0)
    )
    far = Observation.from_arrays(["sphere"] * 3, row(3) + 20.0)
    problem = _problem(demo, unsure, _check(demo, far), unsure)
    edge = _edge_plan(_problem(demo, _answer(demo)))
    assert edge is not None
    plan = replace(edge, reason="done between grid poses")
    assert plan.ambiguous
    assert settle(problem, plan) is plan
    assert settle(_problem(demo, unsure), plan) is plan  # nor is its check rendered


def test_a_rival_the_estimate_itself_prefers_is_rendered_but_its_worse_view_confirms_nothing(
    demo,
):
    """A robust fit nearer another grid pose: that pose is rendered (its own done test may end
    the search there), but its view being worse does not make this one right (near the zenith
    a pose of the target's φ a ring farther off matched better than the rival), so the answer
    stays ambiguous; a rival the estimate has no say on (an unrefined estimate's best
    neighbour) is ruled out by the same view, and the answer confirmed."""
    from services.optimizer.strategies.done import Rival

    answer = _answer(demo)
    far = _check(demo, Observation.from_arrays(["sphere"] * 3, row(3) + 12.0))
    est = Estimate(answer.flat, 15.0, 0.0, 0.4, 0.9)
    comparison = compare_views(answer.observation, TARGET)
    for rival, vindicated in (
        (Rival(far.flat, 0.1, "a robust fit nearer it", settled_by_views=False), False),
        (Rival(far.flat, 0.1, "an unrefined estimate"), True),
    ):
        first = _problem(demo, answer)
        plan = done_plan(first, answer, comparison, est, True, rival=rival)
        assert plan is not None
        assert plan.checks == (far.flat,)
        assert plan.vindicated is vindicated
        moved = settle(first, plan)
        assert not moved.done
        assert moved.next_flat == far.flat
        back = _problem(demo, answer, far, answer)
        settled = settle(back, plan)
        assert settled.done
        assert settled.ambiguous is not vindicated, settled.reason
        if not vindicated:
            assert "yet the estimate prefers it" in settled.reason
