"""The local stack's supervision (``cosmos up``): the backoff between restarts, and a process
that exits started again on its port (a small real process; the whole stack is in
``tests/test_e2e.py``)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from cosmos.launch import free_port, spawn_service, stop_service, wait_healthy
from cosmos.stack import ServicePlan, Supervisor, plan_stack, restart_delay
from services.common.auth import TOKEN_VARIABLE, new_token

FAKE = "tests.controller.fake_replica:app"


def test_the_wait_doubles_up_to_a_cap_and_starts_over_after_a_stable_run():
    waits, previous = [], None
    for _ in range(9):
        previous = restart_delay(previous, uptime_s=1.0)
        waits.append(previous)
    assert waits == [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 30.0]
    assert restart_delay(30.0, uptime_s=59.0) == 30.0
    assert restart_delay(30.0, uptime_s=60.0) == 0.5  # it stayed up: a new failure, a new count
    assert restart_delay(None, uptime_s=0.0, first_s=2.0, max_s=3.0) == 2.0
    assert restart_delay(2.0, uptime_s=0.0, first_s=2.0, max_s=3.0) == 3.0


def test_every_process_of_a_stack_gets_one_token():
    plan = plan_stack(renderers=2, detectors=2, env={"COSMOS_SERVICE_TOKEN": "not this one"})
    tokens = {service.env["COSMOS_SERVICE_TOKEN"] for service in plan}
    assert len(tokens) == 1
    assert tokens != {"not this one"}  # the stack's own, unless given as service_token
    given = "g" * 32
    assert {s.env["COSMOS_SERVICE_TOKEN"] for s in plan_stack(service_token=given)} == {given}
    assert {s.env["COSMOS_SERVICE_TOKEN"] for s in plan_stack()} != tokens  # one per run


@pytest.mark.timeout(120)
def test_an_exited_process_is_started_again_after_its_wait(tmp_path: Path):
    token = new_token()
    plan = ServicePlan("fake", FAKE, free_port(), {"FAKE_NAME": "one", TOKEN_VARIABLE: token})
    first = spawn_service(plan.app, tmp_path, port=plan.port, env=plan.env)
    said: list[str] = []
    supervisor = Supervisor([plan], [first], tmp_path, first_delay_s=0.3, say=said.append)
    try:
        wait_healthy(first)
        supervisor.check()
        assert said == []  # nothing to do while it runs
        os.kill(first.process.pid, signal.SIGKILL)
        first.process.wait(timeout=10)
        supervisor.check()
        assert said == [
            f"fake {first.url} exited (signal 9); starting it again in 0.3 s (log: {first.log})"
        ]
        supervisor.check()
        assert supervisor.processes == (first,)  # still waiting
        time.sleep(0.35)
        supervisor.check()
        (again,) = supervisor.processes
        assert again.url == first.url
        assert again.token == first.token == token  # the stack's token, not a new one
        assert said[-1].startswith(f"fake {first.url} started again (restart 1, pid ")
        wait_healthy(again)
        assert supervisor.restarts(first.url) == 1
        again.process.terminate()  # it exits again soon after: the wait doubles
        again.process.wait(timeout=10)
        supervisor.check()
        assert "starting it again in 0.6 s" in said[-1]
        supervisor.stop()
        time.sleep(0.65)
        supervisor.check()  # stopped: nothing more is started
        assert supervisor.processes == (again,)
        assert first.log.read_text().count("Started server process") == 2  # one log, appended
    finally:
        supervisor.stop()
        for process in supervisor.processes:
            stop_service(process)
