"""Fuzz the running services with the schemathesis CLI, every check on, and say what it found.

Run ``python -m tools.fuzz [--services renderer,optimizer] [--max-examples 50] [--seed 1]``.
It starts the services as real processes on free loopback ports (the whole local stack when the
controller is fuzzed, which needs its stages; else only the stages asked for), then runs, for
each service::

    schemathesis run http://127.0.0.1:PORT/openapi.json --checks all --phases
        examples,coverage,fuzzing,stateful --continue-on-failure -H "Authorization: Bearer …"
        --max-examples N --seed S --generation-database none --report ndjson

with the service token for a stage and the stack's admin API key for the controller, and a
config file (``--config-file``) that draws half the ``scene`` values from the built-in scenes
(:data:`SCENES`). Before the controller is fuzzed, one real search is submitted and its id given
to every ``{search_id}``, so the search routes answer 200 and their schemas get checked, not
only their 404s.

It prints a table per service (operations, requests, failures by check, how many of them
``docs/FUZZING.md`` documents as intended) and every kind of failure with its verdict, and exits
with status 1 when a failure is not documented, 2 when a run did not finish. A failure is a test
case that failed a check, counted once per reason a validation problem gives
(:mod:`tools.fuzz_report`).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

from cosmos.launch import running_service
from cosmos.stack import local_stack
from services.common.auth import TOKEN_VARIABLE, bearer, new_token
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import PoseQuery
from tools.fuzz_report import DOC_PATH, Intended, ServiceRun, load_intended, read_report

__all__ = ["SERVICES", "FuzzedService", "fuzz", "main", "report", "run_schemathesis"]

SERVICES = ("renderer", "detector", "optimizer", "controller")
PHASES = "examples,coverage,fuzzing,stateful"
SCENES = ("demo", "garden")
"""Built-in scenes: half the generated ``scene`` values are one of them, so requests get past
"unknown scene" to renders, detections with a scene's model and plans on a scene's grid, and
their 200 answers are checked against their schemas too."""


def _config(parameters: dict[str, str] | None = None) -> str:
    """schemathesis config (TOML): ``scene`` in a body or query drawn from :data:`SCENES` half
    the time, and ``parameters`` (path parameters) fixed."""
    scenes = ", ".join(f'"{scene}"' for scene in SCENES)
    lines = [
        "[dictionaries.scenes]",
        f"values = [{scenes}]",
        "",
        "[parameters]",
        '"body.scene" = { dictionary = "scenes", probability = 0.5 }',
        '"query.scene" = { dictionary = "scenes", probability = 0.5 }',
        *(f'{name} = "{value}"' for name, value in (parameters or {}).items()),
    ]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class FuzzedService:
    """A running service to fuzz: its URL, what its requests carry, and schemathesis config
    (TOML text, may be empty)."""

    service: str
    url: str
    authorization: str
    config: str = ""
    skip_paths: tuple[str, ...] = ()
    """Paths not fuzzed: streams without end (each request would run into the timeout)."""


def _schemathesis() -> str:
    """The schemathesis CLI of this interpreter's environment."""
    beside = Path(sys.executable).with_name("schemathesis")
    found = str(beside) if beside.exists() else shutil.which("schemathesis")
    if found is None:
        raise RuntimeError("the schemathesis CLI is not installed (pip install -e '.[dev]')")
    return found


def run_schemathesis(
    fuzzed: FuzzedService,
    workdir: Path,
    *,
    max_examples: int,
    seed: int,
    phases: str = PHASES,
    request_timeout_s: float = 60.0,
) -> tuple[Path, int]:
    """Run the CLI with ``--checks all`` on ``fuzzed``; its NDJSON report and exit status.
    The CLI's own output goes to ``<workdir>/<service>.txt``, and it runs in ``workdir``, so
    ``schemathesis replay <test case id>`` reproduces a failure from there."""
    report = workdir / f"{fuzzed.service}.ndjson"
    report.unlink(missing_ok=True)
    command = [_schemathesis()]
    if fuzzed.config:
        config = workdir / f"{fuzzed.service}.toml"
        config.write_text(fuzzed.config, encoding="utf-8")
        command += ["--config-file", str(config)]
    command += [
        "run",
        f"{fuzzed.url}/openapi.json",
        "--checks",
        "all",
        "--phases",
        phases,
        "--continue-on-failure",
        "--header",
        f"Authorization: {fuzzed.authorization}",
        "--max-examples",
        str(max_examples),
        "--seed",
        str(seed),
        "--workers",
        "1",
        "--request-timeout",
        str(request_timeout_s),
        "--generation-database",
        "none",  # each run from its seed alone; nothing left in the working directory
        "--no-color",
        "--report",
        "ndjson",
        "--report-ndjson-path",
        str(report),
    ]
    for path in fuzzed.skip_paths:
        command += ["--exclude-path", path]
    with (workdir / f"{fuzzed.service}.txt").open("w", encoding="utf-8") as out:
        # In the work directory, where the CLI keeps what `st replay <id>` replays.
        done = subprocess.run(
            command, stdout=out, stderr=subprocess.STDOUT, cwd=workdir, check=False
        )
    return report, done.returncode


def _seed_search(controller: str, renderer: str, api_key: str, token: str | None) -> str:
    """Submit one real search (a demo view, two iterations at most); its id."""
    request = RenderRequest(scene="demo", pose=PoseQuery(lat=2, lon=3))
    with httpx.Client(timeout=120.0) as http:
        png = http.post(
            f"{renderer}/render", json=request.model_dump(exclude_none=True), headers=bearer(token)
        )
        png.raise_for_status()
        submitted = http.post(
            f"{controller}/searches",
            params={"scene": "demo", "max_iterations": "2"},
            content=png.content,
            headers={"Content-Type": "image/png", **bearer(api_key)},
        )
        submitted.raise_for_status()
        search_id: str = submitted.json()["id"]
    return search_id


@contextmanager
def running_services(services: Sequence[str], workdir: Path) -> Iterator[list[FuzzedService]]:
    """The services asked for, running: the local stack if the controller is one of them,
    else only those stages, with one service token."""
    with ExitStack() as stack:
        extra: dict[str, FuzzedService] = {}  # the controller's, with its key and seeded search
        if "controller" in services:
            running = stack.enter_context(local_stack(workdir / "stack"))
            token = running.service_token
            urls = {
                "renderer": running.renderers[0],
                "detector": running.detectors[0],
                "optimizer": running.optimizers[0],
            }
            if running.api_key is None:
                raise RuntimeError("the local stack has no API key")
            search_id = _seed_search(running.controller, urls["renderer"], running.api_key, token)
            extra["controller"] = FuzzedService(
                "controller",
                running.controller,
                f"Bearer {running.api_key}",
                _config({"search_id": search_id}),
                # the broker's live health never ends; tests/web/test_routes.py checks it
                skip_paths=("/health/events",),
            )
        else:
            token = new_token()
            urls = {
                name: stack.enter_context(
                    running_service(
                        f"services.{name}.app:app",
                        workdir / "logs",
                        {TOKEN_VARIABLE: token},
                        timeout_s=120.0,
                    )
                ).url
                for name in services
            }
        yield [
            extra.get(name) or FuzzedService(name, urls[name], f"Bearer {token}", _config())
            for name in services
        ]


def _check_counts(run: ServiceRun) -> str:
    counts: Counter[str] = Counter()
    for failure, cases in run.failures.items():
        counts[failure.check] += cases
    return ", ".join(f"{check} {n}" for check, n in sorted(counts.items())) or "none"


def report(runs: dict[str, ServiceRun], intended: list[Intended]) -> tuple[str, int]:
    """The table of ``runs`` and the number of undocumented kinds of failure."""
    lines = [
        f"{'service':<11} {'operations':>10} {'requests':>9}  {'documented':>10} "
        f"{'undocumented':>12}  failures by check"
    ]
    undocumented = 0
    details = []
    for service, run in runs.items():
        documented = run.documented(service, intended)
        missing = run.undocumented(service, intended)
        undocumented += len(missing)
        lines.append(
            f"{service:<11} {run.operations:>10} {run.requests:>9}  "
            f"{sum(run.failures[f] for f in documented):>10} "
            f"{sum(run.failures[f] for f in missing):>12}  {_check_counts(run)}"
        )
        for failure, cases in sorted(run.failures.items(), key=lambda item: str(item[0])):
            row = documented.get(failure)
            verdict = f"intended: {row.why}" if row is not None else "UNDOCUMENTED"
            details.append(
                f"  {service} {failure.operation} {failure.check} {failure.answer} "
                f"({cases} case{'s' if cases != 1 else ''}): {verdict}"
            )
    return "\n".join([*lines, "", "failures:", *(details or ["  none"])]), undocumented


def fuzz(
    services: Sequence[str],
    workdir: Path,
    *,
    max_examples: int,
    seed: int,
    phases: str = PHASES,
) -> tuple[dict[str, ServiceRun], list[str]]:
    """Start ``services`` and run the CLI on each; what each run found, and the services whose
    run did not finish (no report, or a status other than 0 or 1)."""
    runs: dict[str, ServiceRun] = {}
    broken: list[str] = []
    with running_services(services, workdir) as running:
        for fuzzed in running:
            started = time.perf_counter()
            path, status = run_schemathesis(
                fuzzed, workdir, max_examples=max_examples, seed=seed, phases=phases
            )
            print(
                f"{fuzzed.service}: schemathesis exited {status} after "
                f"{time.perf_counter() - started:.0f} s (output: {workdir / fuzzed.service}.txt)",
                flush=True,
            )
            if status not in (0, 1) or not path.exists():
                broken.append(fuzzed.service)
                continue
            runs[fuzzed.service] = read_report(path)
    return runs, broken


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.fuzz", description=__doc__)
    parser.add_argument(
        "--services",
        default=",".join(SERVICES),
        help="comma-separated, of " + ", ".join(SERVICES) + " (default: all)",
    )
    parser.add_argument("--max-examples", type=int, default=50, help="per operation and phase")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--phases", default=PHASES)
    parser.add_argument(
        "--workdir", type=Path, help="keep reports, CLI output and logs here (default: a temp dir)"
    )
    parser.add_argument(
        "--doc",
        type=Path,
        default=DOC_PATH,
        help="the document whose table lists the intended failures",
    )
    args = parser.parse_args(argv)
    services = [s.strip() for s in args.services.split(",") if s.strip()]
    unknown = sorted(set(services) - set(SERVICES))
    if unknown or not services:
        parser.error(f"unknown services {unknown}; choose from {', '.join(SERVICES)}")
    intended = load_intended(args.doc)
    with ExitStack() as stack:
        workdir: Path = args.workdir or Path(
            stack.enter_context(tempfile.TemporaryDirectory(prefix="cosmos-fuzz-"))
        )
        workdir.mkdir(parents=True, exist_ok=True)
        runs, broken = fuzz(
            services, workdir, max_examples=args.max_examples, seed=args.seed, phases=args.phases
        )
        versions = {run.version for run in runs.values()}
        print(
            f"\nschemathesis {', '.join(sorted(versions)) or '?'}, --checks all, "
            f"--max-examples {args.max_examples}, --seed {args.seed}, phases {args.phases}\n"
        )
        table, undocumented = report(runs, intended)
        print(table)
        if broken:
            for service in broken:
                output = (workdir / f"{service}.txt").read_text(errors="replace")
                print(f"\nthe run on {service} did not finish; its output ends:\n{output[-3000:]}")
            return 2
    if undocumented:
        print(f"\n{undocumented} kind(s) of failure not documented in {args.doc}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
