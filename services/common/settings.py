"""Settings helpers shared by the services: one env prefix, a service's own variables read and
checked at start-up, path lists.

A service knows its own variables (its settings class), the shared ones (:data:`SHARED`), the
client side's (:data:`CLIENT_VARIABLES`) and every service's prefix (:data:`SERVICE_PREFIXES`),
and nothing of the other services' settings: a variable under another service's prefix is that
service's business. A ``COSMOS_`` variable under its own prefix that it does not read, or under
no known prefix, is read by no service, a typo most likely, and :func:`from_environment` says so
at start-up instead of ignoring it silently.
"""

from __future__ import annotations

import difflib
import logging
import os
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path
from typing import TypeVar

from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = [
    "API_KEY_VARIABLE",
    "CLIENT_VARIABLES",
    "ENV_PREFIX",
    "SERVICE_PREFIXES",
    "SHARED",
    "ServiceSettings",
    "from_environment",
    "report_unknown_variables",
    "settings_config",
    "split_paths",
    "unknown_variables",
]

ENV_PREFIX = "COSMOS_"

SERVICE_PREFIXES: Mapping[str, str] = {
    service: f"{ENV_PREFIX}{service.upper()}_"
    for service in ("renderer", "detector", "optimizer", "controller")
}
"""Each service's prefix: its own variables, and only its, start with it."""

SHARED = frozenset({"COSMOS_SCENES_DIR", "COSMOS_SERVICE_TOKEN", "COSMOS_SERVICE_AUTH"})
"""Variables several services read, each in the same meaning."""

API_KEY_VARIABLE = "COSMOS_API_KEY"
"""The environment variable a client's API key is read from first."""

CLIENT_VARIABLES: Mapping[str, str] = {
    API_KEY_VARIABLE: "cosmos",
    "COSMOS_TRAINING": "scripts/bootstrap.sh",
}
"""Variables read outside the services, and by what (``cosmos``: the command, as a client of
the controller); a stack's processes see them too, so no service reports them."""

log = logging.getLogger(__name__)


def settings_config() -> SettingsConfigDict:
    """The configuration every service's ``BaseSettings`` uses: ``COSMOS_`` variables, frozen, and
    each field's docstring as its description (``docs/SETTINGS.md`` is written from them)."""
    return SettingsConfigDict(
        env_prefix=ENV_PREFIX, extra="ignore", frozen=True, use_attribute_docstrings=True
    )


class ServiceSettings(BaseSettings):
    """A service's settings: ``COSMOS_`` variables.

    A field's name is its variable's without ``COSMOS_``, so it carries its service's name
    (``renderer_max_side`` is ``COSMOS_RENDERER_MAX_SIDE``); only a variable every reader
    takes in one meaning (``scenes_dir``) is shared."""

    model_config = settings_config()

    @classmethod
    def variables(cls) -> frozenset[str]:
        """The environment variables these settings read."""
        return frozenset(f"{ENV_PREFIX}{name}".upper() for name in cls.model_fields)


Settings = TypeVar("Settings", bound=ServiceSettings)


def _prefix(name: str) -> str | None:
    return next((p for p in SERVICE_PREFIXES.values() if name.startswith(p)), None)


def _known(readers: Iterable[type[ServiceSettings]]) -> tuple[frozenset[str], frozenset[str]]:
    """The variables ``readers`` read, with the shared and the client ones, and their prefixes."""
    variables = frozenset().union(*(settings.variables() for settings in readers))
    prefixes = frozenset(p for name in variables if (p := _prefix(name)) is not None)
    return variables | SHARED | frozenset(CLIENT_VARIABLES), prefixes


def unknown_variables(
    readers: Iterable[type[ServiceSettings]], environ: Mapping[str, str] | None = None
) -> list[str]:
    """The ``COSMOS_`` variables in ``environ`` (default: this process's), sorted, that no
    service reads, as far as ``readers`` (one service's settings, or all four) can tell: those
    under a prefix of theirs that they do not read, and those under no service's prefix that
    are neither shared nor a client's."""
    known, prefixes = _known(readers)
    names = (name.upper() for name in (os.environ if environ is None else environ))
    return sorted(
        name
        for name in names
        if name.startswith(ENV_PREFIX) and name not in known and _prefix(name) in prefixes | {None}
    )


def _hint(name: str, known: Collection[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.8)
    if close:
        return f" (did you mean {close[0]}?)"
    head = name[: name.find("_", len(ENV_PREFIX)) + 1]  # COSMOS_RENDRER_ of COSMOS_RENDRER_X
    close = difflib.get_close_matches(head, SERVICE_PREFIXES.values(), n=1, cutoff=0.8)
    return f" (did you mean {close[0]}{name[len(head) :]}?)" if close else ""


def report_unknown_variables(
    readers: Iterable[type[ServiceSettings]], environ: Mapping[str, str] | None = None
) -> list[str]:
    """Log a warning for each of :func:`unknown_variables`, with the likeliest name meant."""
    readers = list(readers)
    known, _ = _known(readers)
    unknown = unknown_variables(readers, environ)
    for name in unknown:
        log.warning(
            "%s is ignored: no COSMOS 3D Search service reads it%s. docs/SETTINGS.md lists "
            "the variables and who reads each.",
            name,
            _hint(name, known),
        )
    return unknown


def from_environment(settings: type[Settings]) -> Settings:
    """A service's settings read from the environment, once at start-up; any ``COSMOS_``
    variable that no service reads, as far as this one can tell, is reported."""
    loaded = settings()
    report_unknown_variables([settings])
    return loaded


def split_paths(value: str) -> list[Path]:
    """Split an ``os.pathsep``-separated list of directories, skipping empty entries."""
    return [Path(part).expanduser() for part in value.split(os.pathsep) if part.strip()]
