"""The Kubernetes manifests under deploy/k8s: where they are, and how to find things in the
documents a kustomization renders."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from tests.deploy.kustomize import Document
from tests.support import ROOT

__all__ = [
    "IMAGE_SERVICES",
    "K8S",
    "KUSTOMIZATIONS",
    "SECRETS",
    "WORKLOADS",
    "containers",
    "env_of",
    "of_kind",
    "selects",
]

K8S = ROOT / "deploy" / "k8s"
KUSTOMIZATIONS = ("", "external-database")
"""The directories under deploy/k8s that `kubectl apply -k` is pointed at."""
SECRETS = "secrets.env"
IMAGE_SERVICES = ("renderer", "detector", "optimizer", "controller")
"""The services of the project's image (the value of its SERVICE variable)."""
WORKLOADS = ("Deployment", "StatefulSet")


def of_kind(documents: list[Document], kind: str) -> dict[str, Document]:
    return {doc["metadata"]["name"]: doc for doc in documents if doc["kind"] == kind}


def containers(documents: list[Document]) -> Iterator[tuple[Document, dict[str, Any]]]:
    for doc in documents:
        if doc["kind"] in WORKLOADS:
            for container in doc["spec"]["template"]["spec"]["containers"]:
                yield doc, container


def env_of(container: dict[str, Any]) -> dict[str, Any]:
    return {item["name"]: item.get("value", item.get("valueFrom")) for item in container["env"]}


def selects(selector: dict[str, str], workload: Document) -> bool:
    labels = workload["spec"]["template"]["metadata"]["labels"]
    return all(labels.get(key) == value for key, value in selector.items())
