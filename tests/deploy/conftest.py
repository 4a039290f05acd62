"""The deployment files as an engine or a cluster would read them, without either: the compose
file interpolated from ``.env.example`` given values, and each kustomization under
``deploy/k8s/`` rendered with its ``secrets.env`` made from the example beside it."""

from __future__ import annotations

import re
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.deploy.kustomize import Document, build, env_file
from tests.support import ROOT

K8S = ROOT / "deploy" / "k8s"
KUSTOMIZATIONS = ("", "external-database")
"""The directories under deploy/k8s that `kubectl apply -k` is pointed at."""
SECRETS = "secrets.env"
COMPOSE = ROOT / "docker-compose.yml"
COMPOSE_ENV = ROOT / ".env.example"
IMAGE_SERVICES = ("renderer", "detector", "optimizer", "controller")
"""The services of the project's image (the value of its SERVICE variable)."""

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


@pytest.fixture(scope="session")
def compose_env() -> dict[str, str]:
    return filled(env_file(COMPOSE_ENV))


@pytest.fixture(scope="session")
def compose(compose_env: dict[str, str]) -> dict[str, Any]:
    return load_compose(compose_env)


@pytest.fixture(scope="session")
def k8s_copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """deploy/k8s copied, with each secrets.env made from its example (its empty values filled)."""
    copy = tmp_path_factory.mktemp("k8s") / "k8s"
    shutil.copytree(K8S, copy, ignore=shutil.ignore_patterns(SECRETS))
    for example in copy.rglob(f"{SECRETS}.example"):
        pairs = filled(env_file(example))
        example.with_name(SECRETS).write_text("".join(f"{k}={v}\n" for k, v in pairs.items()))
    return copy


@pytest.fixture(scope="session")
def rendered(k8s_copy: Path) -> dict[str, list[Document]]:
    """Each kustomization's documents, by its directory under deploy/k8s."""
    return {name: build(k8s_copy / name) for name in KUSTOMIZATIONS}
