"""docker-compose.yml as `docker compose` reads it: YAML (merge keys included) with its
variables interpolated from an env file."""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import yaml

from tests.support import ROOT

__all__ = ["COMPOSE", "COMPOSE_ENV", "filled", "interpolate", "load_compose"]

COMPOSE = ROOT / "docker-compose.yml"
COMPOSE_ENV = ROOT / ".env.example"

_VARIABLE = re.compile(r"\$(?:\$|\{(?P<name>[A-Za-z_]\w*)(?::?(?P<op>[-?])(?P<arg>[^}]*))?\})")


def filled(env: Mapping[str, str]) -> dict[str, str]:
    """An example env file's pairs with a value, 32 characters long, for each left empty."""
    return {key: value or f"test-{key}-".ljust(32, "x") for key, value in env.items()}


def interpolate(value: Any, env: Mapping[str, str]) -> Any:
    """``value`` (a compose file's data) with ``${NAME}``, ``${NAME:-default}`` and
    ``${NAME:?error}`` replaced as `docker compose` does (``$$`` is a literal ``$``); a
    required variable unset or empty raises ``KeyError`` with its error."""
    if isinstance(value, dict):
        return {key: interpolate(item, env) for key, item in value.items()}
    if isinstance(value, list):
        return [interpolate(item, env) for item in value]
    if not isinstance(value, str):
        return value

    def replace(match: re.Match[str]) -> str:
        name, op, arg = match.group("name", "op", "arg")
        if name is None:
            return "$"
        given = env.get(name, "")
        if op == "?" and not given:
            raise KeyError(f"{name}: {arg}")
        return given or (arg if op == "-" else "")

    return _VARIABLE.sub(replace, value)


def load_compose(env: Mapping[str, str]) -> dict[str, Any]:
    """docker-compose.yml as `docker compose config` sees it with ``env`` as its .env."""
    return interpolate(yaml.safe_load(COMPOSE.read_text()), env)
