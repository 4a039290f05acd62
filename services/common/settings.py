"""Settings helpers shared by the services: one env prefix, renamed variables, path lists."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

__all__ = ["ENV_PREFIX", "RenamedVariables", "ServiceSettings", "settings_config", "split_paths"]

ENV_PREFIX = "COSMOS_"

log = logging.getLogger(__name__)


def settings_config() -> SettingsConfigDict:
    """The configuration every service's ``BaseSettings`` uses: ``COSMOS_`` variables, frozen, and
    each field's docstring as its description (``docs/SETTINGS.md`` is written from them)."""
    return SettingsConfigDict(
        env_prefix=ENV_PREFIX, extra="ignore", frozen=True, use_attribute_docstrings=True
    )


class RenamedVariables(PydanticBaseSettingsSource):
    """Values set under a variable's old name, for the field that replaced it.

    Below the environment in priority, so the new name wins when both are set. Each old name
    found is logged as a warning naming the new one (read once per app, so at start-up).
    """

    def __init__(self, settings_cls: type[BaseSettings], renamed: Mapping[str, str]) -> None:
        super().__init__(settings_cls)
        self.renamed = renamed

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False  # unused: __call__ reads the whole environment at once

    def __call__(self) -> dict[str, Any]:
        environ = {name.upper(): value for name, value in os.environ.items()}
        values: dict[str, Any] = {}
        for old, field in self.renamed.items():
            if old not in environ:
                continue
            new = f"{ENV_PREFIX}{field}".upper()
            if new in environ:
                log.warning("%s is ignored: %s is set. Unset %s.", old, new, old)
                continue
            log.warning(
                "%s is deprecated and will stop working in the next release: a service's "
                "variables now start with its name. This service reads it as %s; set %s "
                "instead.",
                old,
                new,
                new,
            )
            values[field] = environ[old]
        return values


class ServiceSettings(BaseSettings):
    """A service's settings: ``COSMOS_`` variables, and ``renamed`` (old variable → field) still
    read for one release, with a warning.

    A field's name is its variable's without ``COSMOS_``, so it carries its service's name
    (``renderer_max_side`` is ``COSMOS_RENDERER_MAX_SIDE``); only a variable every reader
    takes in one meaning (``scenes_dir``) is shared."""

    model_config = settings_config()

    renamed: ClassVar[Mapping[str, str]] = {}

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        renamed = RenamedVariables(settings_cls, cls.renamed)
        return init_settings, env_settings, renamed, dotenv_settings, file_secret_settings

    @classmethod
    def variables(cls) -> frozenset[str]:
        """The environment variables these settings read (old names in ``renamed`` aside)."""
        return frozenset(f"{ENV_PREFIX}{name}".upper() for name in cls.model_fields)


def split_paths(value: str) -> list[Path]:
    """Split an ``os.pathsep``-separated list of directories, skipping empty entries."""
    return [Path(part).expanduser() for part in value.split(os.pathsep) if part.strip()]
