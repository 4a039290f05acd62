"""Settings helpers shared by the services: one env prefix, path lists, fail-fast validation."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic_settings import SettingsConfigDict

__all__ = ["ENV_PREFIX", "settings_config", "split_paths"]

ENV_PREFIX = "COSMOS_"


def settings_config() -> SettingsConfigDict:
    """The configuration every service's ``BaseSettings`` uses: ``COSMOS_`` variables, frozen."""
    return SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", frozen=True)


def split_paths(value: str) -> list[Path]:
    """Split an ``os.pathsep``-separated list of directories, skipping empty entries."""
    return [Path(part).expanduser() for part in value.split(os.pathsep) if part.strip()]
