"""The outage policy: how a search rides out a stage that no replica serves, and when it fails.

A stage call that no replica serves waits for a replica to answer again (the broker probes the
stage meanwhile) and is made again, for up to ``outage_budget_s`` after it first failed; the
search's time goes into the waiting call's stage time. A search that waited longer fails with
:data:`~services.common.contracts.search.OUTAGE` and can be queued again
(:meth:`~services.controller.runner.SearchRunner.retry`): it resumes from its recorded iterations
like a search after a restart. A stage that refuses a call (a 4xx answer) fails the search at once.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

from services.common.contracts.search import OUTAGE, Search
from services.common.errors import ProblemDetails
from services.controller.broker import BrokerError
from services.controller.failures import SearchFailed, refused
from services.controller.stages import StageError, Stages

__all__ = ["OutagePolicy", "outage", "why_not_retryable"]

_log = logging.getLogger("cosmos.controller")
T = TypeVar("T")


def outage(exc: BrokerError, search_id: str, budget_s: float) -> SearchFailed:
    """The search's failure when no replica of a stage served its task and none came back within
    ``budget_s``: what happened and what to do, in words for whoever submitted it.

    The broker's reasons name replica addresses: they go to the log
    (:meth:`~services.controller.runner.SearchRunner._run`), not into the search's error, which
    every client reads.
    """
    stage = exc.stage
    if exc.reasons:
        what = (
            f"the {stage} was unavailable (no replica could {exc.kind}: each timed out, refused "
            f"the connection or answered with a server error) and did not come back within "
            f"{budget_s:g} s"
        )
    else:
        what = (
            f"no {stage} replica is known (none configured or discovered) and none appeared "
            f"within {budget_s:g} s"
        )
    detail = (
        f"{what}; once GET /health no longer lists the {stage} as unavailable, resume the search "
        f"with POST /searches/{search_id}/retry"
    )
    return SearchFailed(
        ProblemDetails(type=OUTAGE, title=f"No {stage} available", status=503, detail=detail)
    )


def why_not_retryable(search: Search) -> str | None:
    """Why ``search``'s record says it cannot be retried, or None."""
    if search.status != "failed":
        return (
            f"search {search.id} is {search.status}: only a search that failed because a stage "
            "was unavailable can be retried"
        )
    if search.error is None or search.error.type != OUTAGE:
        why = search.error.title if search.error is not None else "no error recorded"
        return (
            f"search {search.id} failed for a reason a retry does not change ({why}); only a "
            "search that failed because a stage was unavailable can be retried"
        )
    return None


class OutagePolicy:
    """Makes a search's stage calls, riding out outages of up to ``budget_s`` seconds."""

    def __init__(self, stages: Stages, budget_s: float) -> None:
        self.stages = stages
        self.budget_s = budget_s

    async def call(self, search_id: str, call: Callable[[], Awaitable[T]]) -> T:
        """``call()``, one stage call of a search, riding out an outage of its stage.

        When no replica serves the call (:class:`BrokerError`), the search waits for one to
        answer again (:meth:`Stages.wait_for_replica`: the broker probes the stage meanwhile)
        and calls again, for up to ``outage_budget_s`` after the first failure. A stage that
        refuses the call, or stays away longer, fails the search.
        """
        since: float | None = None
        while True:
            try:
                answer = await call()
            except StageError as exc:
                raise refused(exc) from exc
            except BrokerError as exc:
                now = time.monotonic()
                if since is None:
                    since = now
                    _log.warning(
                        "search %s waits up to %g s for the %s: %s",
                        search_id,
                        self.budget_s,
                        exc.stage,
                        exc,
                    )
                left = self.budget_s - (now - since)  # exactly the budget at the first failure
                if left <= 0 or not await self.stages.wait_for_replica(exc.stage, left):
                    raise outage(exc, search_id, self.budget_s) from exc
                continue
            if since is not None:
                _log.info("search %s goes on after %.1f s", search_id, time.monotonic() - since)
            return answer
