"""The deployment files as an engine or a cluster would read them, without either: the compose
file interpolated from ``.env.example`` given values, and each kustomization under
``deploy/k8s/`` rendered with its ``secrets.env`` made from the example beside it."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest

from tests.deploy.compose import COMPOSE_ENV, filled, load_compose
from tests.deploy.kustomize import Document, build, env_file
from tests.deploy.manifests import K8S, KUSTOMIZATIONS, SECRETS


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
