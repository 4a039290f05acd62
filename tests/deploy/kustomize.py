"""Render a kustomization as ``kustomize build`` (``kubectl kustomize``) does, for the fields the
manifests under ``deploy/k8s/`` use, so the tests check the documents a cluster would get on a
machine without kubectl (PyPI has no kustomize for Python 3.11; Debian's kubectl is 1.20's).

- ``resources``: YAML files (every document in them) and directories holding a kustomization
  of their own, in order;
- ``secretGenerator``: ``envs`` files (``key=value`` lines; ``#`` comments and blank lines
  skipped) into an ``Opaque`` Secret, values base64-encoded as kustomize writes them, only
  with ``generatorOptions.disableNameSuffixHash`` (the hash is kustomize's own);
- ``images``: ``newName`` and ``newTag`` for the containers whose image has that name, over
  this kustomization's documents and those of the directories it includes.

Any other field is refused, so the loader never quietly differs from kustomize; where kubectl
is installed, ``test_the_loader_builds_what_kustomize_builds`` compares the two.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import yaml

__all__ = ["KUSTOMIZATION", "Document", "build", "env_file"]

KUSTOMIZATION = "kustomization.yaml"
KNOWN_FIELDS = frozenset(
    {"apiVersion", "kind", "resources", "secretGenerator", "generatorOptions", "images"}
)

Document = dict[str, Any]


def build(directory: Path) -> list[Document]:
    """The documents the kustomization in ``directory`` renders."""
    spec = yaml.safe_load((directory / KUSTOMIZATION).read_text())
    unknown = set(spec) - KNOWN_FIELDS
    if unknown:
        where = directory / KUSTOMIZATION
        raise ValueError(f"{where}: the loader does not apply {sorted(unknown)}")
    documents: list[Document] = []
    for resource in spec.get("resources", []):
        path = directory / resource
        if path.is_dir():
            documents += build(path)
        else:
            documents += [doc for doc in yaml.safe_load_all(path.read_text()) if doc]
    documents += _secrets(directory, spec)
    for image in spec.get("images", []):
        _set_image(documents, image)
    return documents


def env_file(path: Path) -> dict[str, str]:
    """The ``key=value`` pairs of an env file as kustomize reads them."""
    pairs = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, separator, value = line.partition("=")
        if not separator:
            raise ValueError(f"{path}: {line!r} is not key=value")
        pairs[key.strip()] = value
    return pairs


def _secrets(directory: Path, spec: dict[str, Any]) -> list[Document]:
    generators = spec.get("secretGenerator", [])
    if generators and not spec.get("generatorOptions", {}).get("disableNameSuffixHash"):
        raise ValueError(f"{directory}: generated names with kustomize's hash suffix")
    secrets = []
    for generator in generators:
        if set(generator) - {"name", "envs"}:
            raise ValueError(f"{directory}: the loader reads a secretGenerator's envs only")
        data: dict[str, str] = {}
        for env in generator["envs"]:
            for key, value in env_file(directory / env).items():
                data[key] = base64.b64encode(value.encode()).decode()
        secrets.append(
            {
                "apiVersion": "v1",
                "kind": "Secret",
                "metadata": {"name": generator["name"]},
                "type": "Opaque",
                "data": data,
            }
        )
    return secrets


def _set_image(documents: list[Document], image: dict[str, str]) -> None:
    for document in documents:
        pod = document.get("spec", {}).get("template", {}).get("spec", {})
        for container in pod.get("containers", []) + pod.get("initContainers", []):
            name, _, tag = container["image"].partition(":")
            if name != image["name"]:
                continue
            tag = image.get("newTag", tag)
            container["image"] = image.get("newName", name) + (f":{tag}" if tag else "")
