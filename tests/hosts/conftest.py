"""The hosts' fixtures: a network of namespaces (:mod:`tests.hosts.network`), deleted whatever
happens to the test, skipped with the reason where namespaces cannot be made, except on CI
(``CI`` set, where the tests run as root), where that fails instead; and ``say``, which writes
a test's figures to the terminal as it goes, output captured or not (so they are in CI's log)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator

import pytest

from tests.hosts.network import Addressing, Network, namespace_problem
from tests.support import skip_unless_on_ci


@pytest.fixture(scope="session")
def namespaces() -> None:
    skip_unless_on_ci(namespace_problem(), "the hosts tests")


@pytest.fixture
def network(namespaces: None) -> Iterator[Network]:
    """A fresh bridge; every host, service and relay on it is gone after the test (and a
    network a killed run left behind is removed when the next one opens)."""
    net = Network(Addressing.from_env())
    try:
        net.open()
        yield net
    finally:
        net.close()


@pytest.fixture
def say(request: pytest.FixtureRequest) -> Callable[[str], None]:
    """Write a line, stamped with the seconds since the test began, to the terminal."""
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    started = time.monotonic()

    def write(line: str) -> None:
        text = f"[{request.node.name[:24]} {time.monotonic() - started:6.1f} s] {line}"
        if reporter is None or capture is None:
            sys.stderr.write(text + "\n")
            return
        with capture.global_and_fixture_disabled():
            reporter.write_line(text)

    return write
