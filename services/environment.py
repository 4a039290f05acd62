"""Every ``COSMOS_`` variable the project reads and who reads it.

Computed from the four services' settings classes (their modules only, so nothing here imports
an app), plus the few variables read outside them.
"""

from __future__ import annotations

from collections.abc import Mapping

from services.common.settings import ENV_PREFIX, ServiceSettings
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
]

SERVICE_SETTINGS: Mapping[str, type[ServiceSettings]] = {
    "renderer": RendererSettings,
    "detector": DetectorSettings,
    "optimizer": OptimizerSettings,
    "controller": ControllerSettings,
}
"""Each service's settings; a service reads ``COSMOS_<SERVICE>_…`` and the :data:`SHARED` ones."""

SHARED = frozenset({"COSMOS_SCENES_DIR"})
"""Variables several services read, each in the same meaning."""

OTHER_READERS: Mapping[str, tuple[str, ...]] = {"COSMOS_TRAINING": ("scripts/bootstrap.sh",)}
"""Variables read outside the services' settings, and by what."""


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
