"""``python -m tools.fuzz``: the schemathesis CLI with ``--checks all`` on a real service, its
report read back, and the table of ``docs/FUZZING.md`` as the gate: a failure it does not list
fails the run."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cosmos.launch import ROOT
from tools.fuzz_report import Failure, Intended, load_intended, read_report

CHECKS = {
    "not_a_server_error",
    "status_code_conformance",
    "content_type_conformance",
    "response_headers_conformance",
    "response_schema_conformance",
    "negative_data_rejection",
    "positive_data_acceptance",
    "missing_required_header",
    "unsupported_method",
    "allow_header_conformance",
    "use_after_free",
    "ensure_resource_availability",
    "ignored_auth",
    "object_level_authorization",
}


def test_every_documented_failure_names_a_service_a_check_and_a_reason():
    rows = load_intended()
    assert len(rows) >= 10
    for row in rows:
        assert row.service in {"renderer", "detector", "optimizer", "controller"}, row
        assert row.check in CHECKS, row
        assert row.operation == "*" or row.operation.split(" ")[0] in {"GET", "POST", "DELETE"}
        assert row.status.isdigit(), row
        assert len(row.why) > 20, row


def test_a_row_covers_its_service_operation_check_and_answer_only():
    row = Intended(
        "optimizer",
        "*",
        "positive_data_acceptance",
        "422",
        "invalid-request",
        "labels must be distinct",
        "why",
    )
    failure = Failure(
        "POST /next-pose",
        "positive_data_acceptance",
        422,
        "invalid-request",
        "Value error, object class labels must be distinct",
    )
    assert row.covers("optimizer", failure)
    assert not row.covers("renderer", failure)
    for other in (
        Failure(
            "POST /next-pose", "negative_data_rejection", 422, "invalid-request", failure.message
        ),
        Failure(
            "POST /next-pose", "positive_data_acceptance", 400, "invalid-request", failure.message
        ),
        Failure(
            "POST /next-pose",
            "positive_data_acceptance",
            422,
            "invalid-request",
            "Input should be a valid integer",
        ),
        Failure("POST /next-pose", "positive_data_acceptance", 422, "box-outside-image"),
    ):
        assert not row.covers("optimizer", other), other


@pytest.mark.slow
def test_the_cli_on_the_optimizer_finds_no_undocumented_failure(tmp_path):
    """About 20 s: the optimizer starts in seconds and the run is small. Its deterministic
    coverage phase meets intended failures (boxes outside their image), so the same report
    against an empty table must not pass."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.fuzz",
            "--services",
            "optimizer",
            "--max-examples",
            "5",
            "--workdir",
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    run = read_report(tmp_path / "optimizer.ndjson")
    assert run.operations == 10
    assert run.requests > 100
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("optimizer ")]
    assert [row[:3] for row in rows] == [["optimizer", "10", str(run.requests)]]
    assert run.failures, "the coverage phase always sends boxes outside their image"
    assert run.undocumented("optimizer", load_intended()) == []
    assert run.undocumented("optimizer", []) == list(run.failures)
    assert "UNDOCUMENTED" not in done.stdout
