"""The local stack: one service token for every process of a run."""

from __future__ import annotations

from services.stack import plan_stack


def test_every_process_of_a_stack_gets_one_token():
    plan = plan_stack(renderers=2, detectors=2, env={"COSMOS_SERVICE_TOKEN": "not this one"})
    tokens = {service.env["COSMOS_SERVICE_TOKEN"] for service in plan}
    assert len(tokens) == 1
    assert tokens != {"not this one"}  # the stack's own, unless given as service_token
    given = "g" * 32
    assert {s.env["COSMOS_SERVICE_TOKEN"] for s in plan_stack(service_token=given)} == {given}
    assert {s.env["COSMOS_SERVICE_TOKEN"] for s in plan_stack()} != tokens  # one per run
