"""Every ``COSMOS_`` variable the project reads and who reads it, so that a service can tell
another's setting (``cosmos up`` gives every process one environment) from a variable nobody
reads, a typo most likely, and say so at start-up instead of ignoring it silently.

Computed from the four services' settings classes (their modules only, so nothing here imports
an app), plus the few variables read outside them.
"""

from __future__ import annotations

import difflib
import logging
import os
from collections.abc import Mapping
from typing import TypeVar

from services.common.settings import ENV_PREFIX, ServiceSettings
from services.controller.keys import API_KEY_VARIABLE
from services.controller.settings import ControllerSettings
from services.detector.settings import DetectorSettings
from services.optimizer.settings import OptimizerSettings
from services.renderer.settings import RendererSettings

__all__ = [
    "OLD_NAMES",
    "OTHER_READERS",
    "READERS",
    "SERVICE_SETTINGS",
    "SHARED",
    "from_environment",
    "report_unknown_variables",
    "unknown_variables",
]

log = logging.getLogger(__name__)

SERVICE_SETTINGS: Mapping[str, type[ServiceSettings]] = {
    "renderer": RendererSettings,
    "detector": DetectorSettings,
    "optimizer": OptimizerSettings,
    "controller": ControllerSettings,
}
"""Each service's settings; a service reads ``COSMOS_<SERVICE>_…`` and the :data:`SHARED` ones."""

SHARED = frozenset({"COSMOS_SCENES_DIR", "COSMOS_SERVICE_TOKEN", "COSMOS_SERVICE_AUTH"})
"""Variables several services read, each in the same meaning."""

OTHER_READERS: Mapping[str, tuple[str, ...]] = {
    API_KEY_VARIABLE: ("cosmos",),
    "COSMOS_TRAINING": ("scripts/bootstrap.sh",),
}
"""Variables read outside the services' settings, and by what (``cosmos``: the command, as a
client of the controller)."""


def _readers() -> dict[str, tuple[str, ...]]:
    readers: dict[str, list[str]] = {}
    for service, settings in SERVICE_SETTINGS.items():
        for name in settings.variables():
            readers.setdefault(name, []).append(service)
    for name, others in OTHER_READERS.items():
        readers.setdefault(name, []).extend(others)
    return {name: tuple(who) for name, who in sorted(readers.items())}


def _old_names() -> dict[str, tuple[str, ...]]:
    new: dict[str, list[str]] = {}
    for settings in SERVICE_SETTINGS.values():
        for old, field in settings.renamed.items():
            new.setdefault(old, []).append(f"{ENV_PREFIX}{field}".upper())
    return {old: tuple(names) for old, names in sorted(new.items())}


READERS: Mapping[str, tuple[str, ...]] = _readers()
"""Each variable, and the services (or scripts) that read it."""

OLD_NAMES: Mapping[str, tuple[str, ...]] = _old_names()
"""Each old name still read for one release, and the names that replaced it (one per reader)."""

Settings = TypeVar("Settings", bound=ServiceSettings)


def unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """The ``COSMOS_`` variables in ``environ`` (default: this process's) that nothing reads,
    neither under its name nor as an old name, sorted."""
    names = (name.upper() for name in (os.environ if environ is None else environ))
    return sorted(
        name
        for name in names
        if name.startswith(ENV_PREFIX) and name not in READERS and name not in OLD_NAMES
    )


def report_unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """Log a warning for each of :func:`unknown_variables`, with the likeliest name meant."""
    unknown = unknown_variables(environ)
    for name in unknown:
        close = difflib.get_close_matches(name, READERS, n=1, cutoff=0.8)
        hint = f" (did you mean {close[0]}?)" if close else ""
        log.warning(
            "%s is ignored: no COSMOS 3D Search service reads it%s. docs/SETTINGS.md lists "
            "the variables and who reads each.",
            name,
            hint,
        )
    return unknown


def from_environment(settings: type[Settings]) -> Settings:
    """A service's settings read from the environment, once at start-up: old names are read with
    a warning each, and any ``COSMOS_`` variable no service reads is reported."""
    loaded = settings()
    report_unknown_variables()
    return loaded
