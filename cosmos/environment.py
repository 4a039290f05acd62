"""Every ``COSMOS_`` variable the project reads and who reads it: the operator's full table
(docs/SETTINGS.md, ``cosmos up``'s check of its environment).

A service checks only its own variables at start-up
(:func:`services.common.settings.from_environment`); ``cosmos``, above the services, knows all
four services' settings and so can tell any variable nobody reads.
"""

from __future__ import annotations

from collections.abc import Mapping

from services.common.settings import CLIENT_VARIABLES, SHARED, ServiceSettings
from services.common.settings import report_unknown_variables as _report
from services.common.settings import unknown_variables as _unknown
from services.controller.settings import ControllerSettings
from services.detector.settings import DetectorSettings
from services.optimizer.settings import OptimizerSettings
from services.renderer.settings import RendererSettings

__all__ = [
    "READERS",
    "SERVICE_SETTINGS",
    "SHARED",
    "report_unknown_variables",
    "unknown_variables",
]

SERVICE_SETTINGS: Mapping[str, type[ServiceSettings]] = {
    "renderer": RendererSettings,
    "detector": DetectorSettings,
    "optimizer": OptimizerSettings,
    "controller": ControllerSettings,
}
"""Each service's settings; a service reads ``COSMOS_<SERVICE>_…`` and the :data:`SHARED` ones."""


def _readers() -> dict[str, tuple[str, ...]]:
    readers: dict[str, list[str]] = {}
    for service, settings in SERVICE_SETTINGS.items():
        for name in settings.variables():
            readers.setdefault(name, []).append(service)
    for name, other in CLIENT_VARIABLES.items():
        readers.setdefault(name, []).append(other)
    return {name: tuple(who) for name, who in sorted(readers.items())}


READERS: Mapping[str, tuple[str, ...]] = _readers()
"""Each variable, and the services (or scripts) that read it."""


def unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """The ``COSMOS_`` variables in ``environ`` (default: this process's) that nothing reads,
    sorted."""
    return _unknown(SERVICE_SETTINGS.values(), environ)


def report_unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """Log a warning for each of :func:`unknown_variables`, with the likeliest name meant."""
    return _report(SERVICE_SETTINGS.values(), environ)
