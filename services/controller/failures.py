"""Why a search cannot go on: :class:`SearchFailed` and the problems it carries, in words for
whoever submitted the search."""

from __future__ import annotations

from pydantic import ValidationError

from services.common.errors import ProblemDetails, problem_type
from services.controller.stages import StageError

__all__ = ["SearchFailed", "failure", "refused", "unreadable_answer"]


class SearchFailed(Exception):
    """A search cannot go on; ``problem`` says why."""

    def __init__(self, problem: ProblemDetails) -> None:
        super().__init__(problem.detail)
        self.problem = problem


def failure(slug: str, title: str, detail: str, status: int = 502) -> SearchFailed:
    return SearchFailed(
        ProblemDetails(type=problem_type(slug), title=title, status=status, detail=detail)
    )


def refused(exc: StageError) -> SearchFailed:
    """The search's failure when a stage refused its task (a 4xx answer)."""
    problem = exc.problem
    detail = f"the {exc.stage} refused a task: {problem.detail or problem.title}"
    return failure("stage-refused", f"{exc.stage.capitalize()} refused", detail, 422)


def unreadable_answer(exc: ValidationError) -> SearchFailed:
    """The search's failure when the optimizer's answer does not fit the contract: the fields
    at fault, without pydantic's dump of the answer."""
    errors = [
        {"field": ".".join(str(part) for part in err["loc"]), "message": err["msg"]}
        for err in exc.errors(include_url=False, include_context=False, include_input=False)
    ]
    named = "; ".join(f"{err['field']}: {err['message']}" for err in errors[:3])
    more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
    detail = (
        f"the optimizer's answer does not fit this controller's contract ({named}{more}); "
        "the optimizer and the controller are probably of different versions"
    )
    problem = ProblemDetails(
        type=problem_type("bad-optimizer-answer"),
        title="Bad optimizer answer",
        status=502,
        detail=detail,
        errors=errors,
    )
    return SearchFailed(problem)
