"""What a schemathesis CLI run found, read from its NDJSON report, and which of it is intended.

A run's report (``schemathesis run --report ndjson``) holds one event per line; each finished
scenario records the operation, every request and answer (``interactions``) and every check's
verdict per test case. :func:`read_report` counts the requests and collects each failed check
with the answer that failed it: the status and, for a problem+json body, its ``type``
(``urn:cosmos:problem:<slug>``). Schema errors (``NonFatalError``) count as failures of the
pseudo-check ``error``.

A failure is *documented as intended* when a row of the table in ``docs/FUZZING.md`` (between
:data:`TABLE_START` and :data:`TABLE_END`) names its service, operation (or ``*``), check and
answer (``422 box-outside-image``; ``*`` for any slug; ``422 invalid-request: <text>`` for a
generic problem whose message holds the text), with the reason in the last column.
"""

from __future__ import annotations

import base64
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "DOC_PATH",
    "TABLE_END",
    "TABLE_START",
    "Failure",
    "Intended",
    "ServiceRun",
    "load_intended",
    "read_report",
]

DOC_PATH = Path(__file__).resolve().parents[1] / "docs" / "FUZZING.md"
TABLE_START = "<!-- intended failures: start -->"
TABLE_END = "<!-- intended failures: end -->"
_PROBLEM_PREFIX = "urn:cosmos:problem:"


@dataclass(frozen=True)
class Failure:
    """One kind of failed check: where, which check, and the answer that failed it (``slug``:
    the problem type's last part, ``-`` for an answer that is not a COSMOS problem; ``message``:
    for an ``invalid-request`` or ``bad-request`` problem, one of its errors' messages (the
    field left out), or its detail when it lists no errors)."""

    operation: str
    check: str
    status: int | None
    slug: str
    message: str = ""

    @property
    def answer(self) -> str:
        status = self.status if self.status is not None else "-"
        return f"{status} {self.slug}" + (f": {self.message}" if self.message else "")


@dataclass(frozen=True)
class Intended:
    """A row of the documented table: a failure that is meant, and why."""

    service: str
    operation: str
    check: str
    status: str
    slug: str
    message: str
    why: str

    def covers(self, service: str, failure: Failure) -> bool:
        return (
            self.service == service
            and self.operation in ("*", failure.operation)
            and self.check == failure.check
            and self.status in ("*", str(failure.status))
            and self.slug in ("*", failure.slug)
            and self.message in failure.message
        )


@dataclass
class ServiceRun:
    """What one CLI run on one service found."""

    operations: int = 0
    requests: int = 0
    failures: Counter[Failure] = field(default_factory=Counter)
    """Each kind of failure and how many test cases met it."""
    seed: str = ""
    version: str = ""

    def documented(self, service: str, intended: list[Intended]) -> dict[Failure, Intended]:
        """The failures a row of ``intended`` covers, with that row."""
        found = {}
        for failure in self.failures:
            row = next((row for row in intended if row.covers(service, failure)), None)
            if row is not None:
                found[failure] = row
        return found

    def undocumented(self, service: str, intended: list[Intended]) -> list[Failure]:
        covered = self.documented(service, intended)
        return [failure for failure in self.failures if failure not in covered]


def _slug(body: Any) -> str:
    if isinstance(body, dict) and isinstance(body.get("type"), str):
        kind: str = body["type"]
        return kind.removeprefix(_PROBLEM_PREFIX) if kind.startswith(_PROBLEM_PREFIX) else "-"
    return "-"


_GENERIC = frozenset({"invalid-request", "bad-request"})
"""Problem types that say little alone: their messages tell one refusal from another."""


def _messages(body: Any) -> list[str]:
    """The distinct messages of a generic problem's (:data:`_GENERIC`) ``errors``, or its
    ``detail`` when it lists none (nothing for another answer: its type says enough)."""
    if _slug(body) not in _GENERIC:
        return [""]
    errors = body.get("errors")
    if not isinstance(errors, list):
        return [str(body.get("detail", ""))]
    found = {str(e.get("message", "")) for e in errors if isinstance(e, dict)}
    return sorted(found) or [""]


def _answer(interaction: dict[str, Any] | None) -> tuple[int | None, str, list[str]]:
    """The status, problem slug and validation messages of a recorded answer."""
    response = (interaction or {}).get("response") or {}
    status = response.get("status_code")
    content = response.get("content") or {}
    raw = content.get("$base64")
    try:
        text = base64.b64decode(raw) if isinstance(raw, str) else content.get("string", b"")
        body = json.loads(text) if text else None
    except ValueError:
        body = None
    return (status if isinstance(status, int) else None), _slug(body), _messages(body)


def read_report(path: Path) -> ServiceRun:
    """The operations, requests and failures of the NDJSON report at ``path``."""
    run = ServiceRun()
    with path.open(encoding="utf-8") as lines:
        for line in lines:
            if not line.strip():
                continue
            event: dict[str, Any] = json.loads(line)
            ((kind, body),) = event.items()
            if kind == "Initialize":
                run.seed = str(body.get("seed", ""))
                run.version = str(body.get("schemathesis_version", ""))
            elif kind == "LoadingFinished":
                run.operations = int(body["statistic"]["operations"]["selected"])
            elif kind == "NonFatalError":
                message = str(body.get("value", {}).get("type", "error"))
                run.failures[Failure(str(body.get("label", "?")), "error", None, message)] += 1
            elif kind == "ScenarioFinished":
                _read_scenario(run, body.get("recorder") or {})
    return run


def _read_scenario(run: ServiceRun, recorder: dict[str, Any]) -> None:
    interactions: dict[str, Any] = recorder.get("interactions") or {}
    run.requests += len(interactions)
    default = str(recorder.get("label", "?"))
    cases: dict[str, Any] = recorder.get("cases") or {}
    for case_id, checks in (recorder.get("checks") or {}).items():
        case = (cases.get(case_id) or {}).get("value") or {}
        operation = default
        if " /" not in default and "method" in case and "path" in case:  # a stateful scenario
            operation = f"{case['method']} {case['path']}"
        for check in checks:
            if check.get("status") != "failure":
                continue
            status, slug, messages = _answer(interactions.get(case_id))
            for message in messages:  # each reason to refuse must be an intended one
                run.failures[Failure(operation, str(check["name"]), status, slug, message)] += 1


def load_intended(path: Path = DOC_PATH) -> list[Intended]:
    """The rows of the intended-failures table in ``path`` (none if it has no table)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    if TABLE_START not in text or TABLE_END not in text:
        return []
    table = text.split(TABLE_START, 1)[1].split(TABLE_END, 1)[0]
    rows = []
    for line in table.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 5 or cells[0] in ("service", "") or set(cells[0]) <= {"-", ":"}:
            continue
        service, operation, check, answer = (cell.strip("`") for cell in cells[:4])
        why = cells[4]
        answer, _, message = answer.partition(": ")
        status, _, slug = answer.partition(" ")
        rows.append(
            Intended(service, operation, check, status, slug.strip() or "*", message.strip(), why)
        )
    return rows
