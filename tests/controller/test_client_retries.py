"""``ControllerClient.submit``'s waiting on its own, against scripted answers (no stack): which
refusals it waits out, how long each wait is, and where its budget ends it. The same policy
against a real stack is ``test_client.py``'s (slow)."""

from __future__ import annotations

import httpx
import pytest

from services.common.contracts.optimize import GridPose
from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex
from services.controller.client import ControllerClient, ControllerError
from services.controller.store import utcnow

TAKEN = Search(
    id="taken",
    status="queued",
    scene="demo",
    strategy="reprojection",
    start=GridPose(index=GridIndex(lat=3, lon=0), theta_deg=30.0, phi_deg=0.0),
    seed=1,
    max_iterations=5,
    created_at=utcnow(),
    updated_at=utcnow(),
    target_size=(32, 24),
)


def refusal(status: int, retry_after: str | None = None) -> httpx.Response:
    headers = {} if retry_after is None else {"Retry-After": retry_after}
    return httpx.Response(status, json={"detail": f"refused {status}"}, headers=headers)


def scripted(*answers: httpx.Response) -> tuple[ControllerClient, list[httpx.Request]]:
    """A client whose controller gives ``answers`` in turn, then takes the search."""
    asked: list[httpx.Request] = []

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request)
        if len(asked) <= len(answers):
            return answers[len(asked) - 1]
        return httpx.Response(202, content=TAKEN.model_dump_json())

    client = ControllerClient("http://controller")
    client._http = httpx.Client(base_url="http://controller", transport=httpx.MockTransport(answer))
    return client, asked


def submit(client: ControllerClient, **kwargs: float) -> tuple[Search, list[float], list]:
    slept: list[float] = []
    heard: list[tuple[int, float]] = []
    search = client.submit(
        b"\x89PNG\r\n\x1a\n",
        "demo",
        sleep=slept.append,
        on_wait=lambda refused, wait_s: heard.append((refused.status, wait_s)),
        **kwargs,
    )
    return search, slept, heard


def test_refusals_with_retry_after_are_waited_out_each_at_least_half_a_second_and_at_most_the_cap():
    client, asked = scripted(
        refusal(503, "2"), refusal(429, "0"), refusal(429, "30"), refusal(503, "1")
    )
    search, slept, heard = submit(client, max_iterations=3)
    assert search == TAKEN
    assert slept == [2.0, 0.5, 10.0, 1.0]  # Retry-After, at least 0.5 s, at most max_wait_s
    assert heard == [(503, 2.0), (429, 0.5), (429, 10.0), (503, 1.0)]
    assert len(asked) == 5
    assert asked[-1].url.params["max_iterations"] == "3"


def test_the_budget_ends_the_waiting_before_a_wait_that_would_pass_it():
    client, asked = scripted(*[refusal(429, "5")] * 3)
    with pytest.raises(ControllerError) as ended:
        submit(client, retry_budget_s=12.0)
    assert (ended.value.status, ended.value.detail) == (429, "refused 429")
    assert ended.value.waited_s == 10.0  # 5 + 5; another 5 would pass 12
    assert len(asked) == 3


@pytest.mark.parametrize("budget_s", [0.0, 4.0])
def test_a_refusal_beyond_the_budget_ends_at_once(budget_s):
    client, asked = scripted(refusal(429, "5"))
    with pytest.raises(ControllerError) as ended:
        submit(client, retry_budget_s=budget_s)
    assert (ended.value.retry_after_s, ended.value.waited_s, len(asked)) == (5.0, 0.0, 1)


@pytest.mark.parametrize(
    "answer", [refusal(404), refusal(503), refusal(500, "1"), refusal(401, "1")], ids=repr
)
def test_other_refusals_are_not_asked_again(answer):
    client, asked = scripted(answer)
    with pytest.raises(ControllerError) as ended:
        submit(client)
    assert ended.value.status == answer.status_code
    assert len(asked) == 1


def test_a_refusal_after_waits_says_how_long_was_waited():
    client, _ = scripted(refusal(503, "1"), refusal(404))
    with pytest.raises(ControllerError) as ended:
        submit(client)
    assert (ended.value.status, ended.value.waited_s) == (404, 1.0)


def test_nonsense_budgets_are_refused():
    client, _ = scripted()
    with pytest.raises(ValueError, match="retry_budget_s"):
        submit(client, retry_budget_s=-1.0)
    with pytest.raises(ValueError, match="max_wait_s"):
        submit(client, max_wait_s=0.0)
