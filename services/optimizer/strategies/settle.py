"""An ambiguous answer settled by rendering what its estimate could not rule out
(``reprojection``).

A done answer is ambiguous when its estimate cannot tell its grid pose A from a few others
(:mod:`.done`: an estimate near the boundary with a neighbour, a σ that reaches it, a robust fit
nearer another pose) or when the map scores distant poses alike (:mod:`.map_based`). Those are
its *checks* (:attr:`~services.optimizer.problem.Plan.checks`). The search still has renders,
and their views tell what the estimate could not: a view of the pose the target was taken from
passes the loose done test (a JPEG or photo target at the true pose does, 99 % of the time),
another pose's view, a step or more away, need not. So, when A's own view passes the loose test
(an answer done on the map's prediction between grid poses, its view farther off, has no view to
vouch for it), for at most :data:`MAX_CHECKS` checks:

1. at A, with a check B not seen yet, the search goes to B instead of ending;
2. at B, B's own done test decides when it passes (an on-grid target ends there by the strict
   test); else the search goes on to the next check not seen yet, and from the last back to A,
   seen before, so not rendered again (:func:`next_check`): A is seen twice, whatever the
   number of checks;
3. back at A, on A's done plan as first made (:func:`settling`; the map has changed since),
   every check seen, A stands alone when each check's view is *ruled out*: it fails the loose
   test, whole and without its worst pair, and its RMS exceeds A's own by more than its edge
   noise, ``rms_B > rms_A + N_B`` (both views are compared with one target, so a gap beyond the
   noise is the poses' difference). Otherwise A stays ambiguous, saying which checks match too.
   So does an A whose estimate itself prefers a check (a robust fit nearer it,
   :attr:`~services.optimizer.problem.Plan.vindicated`): near the zenith a view's box RMS
   follows φ more than θ, and such an A two rings from the target was confirmed over the
   rival a ring away (seed 10 below); the rival is still rendered, and ends the search when
   its own done test passes.

Fewer pairs than ``MIN_ESTIMATE_PAIRS`` under the estimate, or a map matching fewer than two
target detections, leave the pose open wider than a few neighbours; such answers have no checks
(None) and end as they are.

Measured with the general model on generated scenes (``cosmos bench --random-scenes 5 --n 5
--onboard none --starts given,predicted --seed 7``, 300 searches, one run each way): confirmed
right 177 → 204, found 282 → 283, confirmed wrong 0 either way, renders a search 4.30 → 4.41 on
average. An answer whose estimate prefers its check is no longer confirmed by the check's worse
view (same command, one run each way): confirmed wrong 2 → 0 on seed 10, every other figure on
seeds 7–10 unchanged (confirmed right 221, 264, 274 and 254; found 283, 294, 295 and 286).
The checks were first rendered each followed by a return to A, which the optimizer's rule on
poses seen three times held to two checks; in a row, A is seen twice, and the map's alike
distant poses (at most five) alone are always settled. Same command, seeds 7–10 (one run each way):
confirmed right with a given start 112 → 114, 131 → 139, 135 → 138 and 124 → 129, with a
predicted one 109 → 115, 133 → 139, 139 → 140 and 130 → 136; found 1 more (seed 8); confirmed
wrong 0; renders a search 0.1–0.26 more on average, the median with a predicted start still 1.
Settling on the views alone, without A's own view passing and A's first plan, had let
two answers be confirmed wrong (the general model's view at the true pose, one object boxed
twice, was worse than the answer's) and sent others wandering for 20 renders.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Final

from services.optimizer.matching import compare_views
from services.optimizer.observations import Observation
from services.optimizer.problem import Plan, SearchProblem, Visit
from services.optimizer.strategies.done import loose_tolerance, one_object_changed
from services.optimizer.strategies.moves import move_between

__all__ = ["MAX_CHECKS", "Settling", "next_check", "settle", "settling"]

MAX_CHECKS: Final = 5
"""An answer with more checks than this is not settled; each check costs one render. The map
flags at most five distant alternatives (``map_based``): the map's ambiguity alone is always
settled."""


def _checks(plan: Plan) -> tuple[int, ...] | None:
    """The checks that may settle ``plan`` (module docstring), or None when it is not an
    ambiguous done plan that views can settle."""
    if not (plan.done and plan.ambiguous) or not plan.checks:
        return None
    checks = tuple(f for f in dict.fromkeys(plan.checks) if f != plan.next_flat)
    return checks if 0 < len(checks) <= MAX_CHECKS else None


def _unseen(problem: SearchProblem, checks: tuple[int, ...]) -> list[int]:
    """The ``checks`` no view of the search has seen yet, in order."""
    seen = {v.flat for v in problem.history}
    return [f for f in checks if f not in seen]


def _view_match(problem: SearchProblem, observation: Observation) -> tuple[float, bool, float]:
    """A view's match with the target: its RMS (the smallest of the whole match's and those as
    if one object changed, :func:`~.done.one_object_changed`; ∞ with no pair), whether any
    passes the loose done test, and the whole match's edge noise ``N``."""
    comparison = compare_views(observation, problem.target)
    rms, passes = math.inf, False
    for match in (comparison, *one_object_changed(problem, observation, comparison)):
        if not match.pairs:
            continue
        rms = min(rms, match.rms_px)
        loose = loose_tolerance(match, problem.tolerance_px)
        passes = passes or match.within(loose, problem.max_unmatched)
    return rms, passes, comparison.noise_px


def _at(problem: SearchProblem, flat: int) -> str:
    index = problem.grid.unflat(flat)
    return f"lat {index.lat} lon {index.lon}"


def _rms_text(rms: float) -> str:
    return f"RMS {rms:.2f} px" if math.isfinite(rms) else "no pair"


def settle(problem: SearchProblem, plan: Plan) -> Plan:
    """``plan``, a done plan at the current pose, settled by its checks' views (module
    docstring): a move to the first check not seen yet; once all are seen, the plan no longer
    ambiguous when every check is ruled out, else as ambiguous as it was. Any other plan, and
    one whose own view fails the loose test (the images would not vouch for it), is returned
    as it is."""
    checks = _checks(plan)
    current = problem.current
    if checks is None or current is None:
        return plan
    own, passes, _ = _view_match(problem, current.observation)
    if not passes:
        return plan
    seen = {v.flat: v for v in problem.history}
    pending = _unseen(problem, checks)
    if pending:
        nxt = pending[0]
        return replace(
            plan,
            done=False,
            next_flat=nxt,
            move=move_between(problem.grid, current.flat, nxt),
            reason=f"{plan.reason}; rendering {_at(problem, nxt)} to settle it",
        )
    standing: list[str] = []
    ruled_out: list[str] = []
    for flat in checks:
        rms, passes, noise = _view_match(problem, seen[flat].observation)
        text = f"{_at(problem, flat)} ({_rms_text(rms)})"
        if passes or not rms > own + noise:
            standing.append(text)
        else:
            ruled_out.append(text)
    if standing:
        return replace(
            plan,
            reason=f"{plan.reason}; rendered to settle it, the view of "
            f"{', '.join(standing)} matches the target too",
        )
    if not plan.vindicated:
        return replace(
            plan,
            reason=f"{plan.reason}; rendered to settle it, the view of {', '.join(ruled_out)} "
            f"matches the target worse than this one ({_rms_text(own)}), yet the estimate "
            "prefers it: the images do not decide",
        )
    return replace(
        plan,
        ambiguous=False,
        alternatives=(),
        checks=None,
        reason=f"{plan.reason.replace('; ambiguous: ', '; undecided by the estimate: ')}; "
        f"settled by rendering: the view of {', '.join(ruled_out)} does not match the target, "
        f"this one does better ({_rms_text(own)})",
    )


@dataclass(frozen=True)
class Settling:
    """An answer being settled: its visit, and its done plan as made when it was first seen."""

    answer: Visit
    plan: Plan


def settling(
    problem: SearchProblem, plan_at: Callable[[tuple[Visit, ...]], Plan | None]
) -> Settling | None:
    """The answer the latest visits settle, if any: a visit whose done plan (``plan_at`` its
    history up to it, so the map it was made on) has checks that its own view vouches for,
    followed only by distinct checks of it, and at most one return to it, the last visit."""
    history = problem.history
    n = len(history)
    for j in range(max(n - MAX_CHECKS - 2, 0), n - 1):
        answer, after = history[j], history[j + 1 :]
        if after[-1].flat == answer.flat:
            after = after[:-1]
        flats = [v.flat for v in after]
        if not flats or answer.flat in flats or len(set(flats)) < len(flats):
            continue
        if not _view_match(problem, answer.observation)[1]:
            continue
        plan = plan_at(history[: j + 1])
        checks = None if plan is None else _checks(plan)
        if plan is not None and checks and all(f in checks for f in flats):
            return Settling(answer, plan)
    return None


def next_check(problem: SearchProblem, answer: Settling) -> Plan:
    """At a check whose own done test failed, the move to the ``answer``'s next check not seen
    yet, or, all seen, back to the answer (seen before: no render)."""
    current = problem.current
    assert current is not None
    rms, _, _ = _view_match(problem, current.observation)
    pending = _unseen(problem, _checks(answer.plan) or ())
    nxt = pending[0] if pending else answer.answer.flat
    where = f"on to {_at(problem, nxt)}" if pending else "back there (seen before: no render)"
    return replace(
        answer.plan,
        done=False,
        next_flat=nxt,
        move=move_between(problem.grid, current.flat, nxt),
        reason=f"this view, rendered to settle the answer at {_at(problem, answer.answer.flat)}"
        f", is not done ({_rms_text(rms)}); {where}",
    )
