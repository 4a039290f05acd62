"""The Kubernetes manifests (deploy/k8s, kustomize) as a cluster would get them: every document
valid against the Kubernetes API schemas (kubernetes-validate, offline), and the pieces fitting
together: probes and requests on every container, the stages behind headless Services the
controller's broker resolves, autoscalers, disruption budgets, the Secret's keys, and only
settings the services read."""

from __future__ import annotations

import base64
import copy
import shutil
import subprocess
from pathlib import Path
from urllib.parse import urlsplit

import kubernetes_validate
import pytest
import yaml

from cosmos.environment import SERVICE_SETTINGS
from tests.deploy.image import dockerfile_user_id
from tests.deploy.kustomize import Document, build, env_file
from tests.deploy.manifests import (
    IMAGE_SERVICES,
    K8S,
    KUSTOMIZATIONS,
    SECRETS,
    WORKLOADS,
    containers,
    env_of,
    of_kind,
    selects,
)
from tests.support import ROOT

OLDEST_KUBERNETES = "1.29"
"""The oldest Kubernetes the manifests are checked against (HPA autoscaling/v2 and PDB policy/v1
are GA there), besides the newest kubernetes-validate knows."""

STAGES = ("renderer", "detector", "optimizer")


@pytest.fixture(params=KUSTOMIZATIONS, ids=lambda name: name or "k8s")
def documents(request: pytest.FixtureRequest, rendered: dict[str, list[Document]]):
    return rendered[request.param]


def test_the_loader_builds_what_kustomize_builds(k8s_copy: Path, rendered):
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl (with kustomize) is not installed: the loader alone renders")
    for name in KUSTOMIZATIONS:
        built = subprocess.run(
            [kubectl, "kustomize", str(k8s_copy / name)],
            capture_output=True,
            text=True,
            check=True,
            timeout=60,
        ).stdout
        by_kustomize = [doc for doc in yaml.safe_load_all(built) if doc]
        key = lambda doc: (doc["kind"], doc["metadata"]["name"])  # noqa: E731
        assert sorted(rendered[name], key=key) == sorted(by_kustomize, key=key), name


def test_the_loader_refuses_what_it_does_not_apply(tmp_path: Path):
    (tmp_path / "kustomization.yaml").write_text("resources: []\nnamePrefix: cosmos-\n")
    with pytest.raises(ValueError, match="namePrefix"):
        build(tmp_path)


@pytest.mark.parametrize("version", [OLDEST_KUBERNETES, kubernetes_validate.latest_version()])
def test_every_document_is_valid_against_the_kubernetes_schemas(documents, version):
    kinds = set()
    for doc in documents:
        kubernetes_validate.validate(doc, version, strict=True)
        kinds.add(doc["kind"])
    assert {"Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget"} <= kinds
    assert "Secret" in kinds


def test_the_schemas_refuse_a_misspelt_field(rendered):
    deployment = copy.deepcopy(of_kind(rendered[""], "Deployment")["renderer"])
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    container["readinesProbe"] = container.pop("readinessProbe")
    with pytest.raises(kubernetes_validate.ValidationError, match="readinesProbe"):
        kubernetes_validate.validate(deployment, OLDEST_KUBERNETES, strict=True)


def test_the_stack_has_every_service_and_postgres_only_in_the_cluster(rendered):
    for name, documents in rendered.items():
        deployments = of_kind(documents, "Deployment")
        assert sorted(deployments) == sorted(IMAGE_SERVICES), name
    assert list(of_kind(rendered[""], "StatefulSet")) == ["postgres"]
    assert of_kind(rendered["external-database"], "StatefulSet") == {}


def test_every_container_has_probes_and_resource_requests(documents):
    for workload, container in containers(documents):
        where = f"{workload['metadata']['name']}/{container['name']}"
        assert {"cpu", "memory"} <= set(container["resources"]["requests"]), where
        assert "memory" in container["resources"]["limits"], where
        for probe in ("readinessProbe", "livenessProbe"):
            assert probe in container, f"{where} has no {probe}"
        if workload["metadata"]["name"] == "postgres":
            continue
        # docs/OPERATIONS.md: liveness on /livez (never /readyz), readiness on /readyz
        assert container["livenessProbe"]["httpGet"]["path"] == "/livez", where
        assert container["readinessProbe"]["httpGet"]["path"] == "/readyz", where
        ports = {port["name"] for port in container["ports"]}
        for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
            if probe in container:
                assert container[probe]["httpGet"]["port"] in ports, f"{where} {probe}"


def test_the_image_runs_each_service_on_its_container_port_as_its_user(documents):
    for workload, container in containers(documents):
        if workload["metadata"]["name"] == "postgres":
            continue
        env = env_of(container)
        assert env["SERVICE"] in IMAGE_SERVICES
        assert container["image"].startswith("cosmos-3d-search:")
        assert [port["containerPort"] for port in container["ports"]] == [int(env["PORT"])]
        security = workload["spec"]["template"]["spec"]["securityContext"]
        assert security["runAsUser"] == dockerfile_user_id()


def test_every_cosmos_variable_is_one_its_service_reads(documents):
    seen = set()
    for workload, container in containers(documents):
        if workload["metadata"]["name"] == "postgres":
            continue
        env = env_of(container)
        reads = SERVICE_SETTINGS[env["SERVICE"]].variables()
        cosmos = {name for name in env if name.startswith("COSMOS_")}
        assert cosmos <= reads, f"{env['SERVICE']} does not read {sorted(cosmos - reads)}"
        assert "COSMOS_SERVICE_TOKEN" in cosmos, env["SERVICE"]
        seen |= cosmos
    assert "COSMOS_CONTROLLER_DATABASE_URL" in seen


def test_the_controller_finds_each_stage_through_its_headless_service(documents):
    services = of_kind(documents, "Service")
    deployments = of_kind(documents, "Deployment")
    [controller] = [c for w, c in containers(documents) if w["metadata"]["name"] == "controller"]
    env = env_of(controller)
    assert env["COSMOS_CONTROLLER_DISCOVER_REPLICAS"] == "true"
    for stage in STAGES:
        [url] = env[f"COSMOS_CONTROLLER_{stage.upper()}_URLS"].split(",")
        parts = urlsplit(url)
        service = services[parts.hostname]
        # services/controller/discovery.py: one replica per address the name resolves to,
        # which only a headless Service's DNS gives (a ClusterIP is one address).
        assert service["spec"]["clusterIP"] == "None", stage
        assert [port["port"] for port in service["spec"]["ports"]] == [parts.port]
        assert selects(service["spec"]["selector"], deployments[stage])


def test_every_service_selects_one_workload_on_a_port_it_has(documents):
    workloads = [doc for doc in documents if doc["kind"] in WORKLOADS]
    for name, service in of_kind(documents, "Service").items():
        [workload] = [w for w in workloads if selects(service["spec"]["selector"], w)]
        [container] = workload["spec"]["template"]["spec"]["containers"]
        port_names = {port["name"] for port in container["ports"]}
        for port in service["spec"]["ports"]:
            assert port["targetPort"] in port_names, name


def test_renderers_and_detectors_autoscale_and_every_workload_has_a_budget(documents):
    deployments = of_kind(documents, "Deployment")
    autoscalers = of_kind(documents, "HorizontalPodAutoscaler")
    assert sorted(autoscalers) == ["detector", "renderer"]
    for name, autoscaler in autoscalers.items():
        target = autoscaler["spec"]["scaleTargetRef"]
        assert (target["kind"], target["name"]) == ("Deployment", name)
        # kubectl apply would reset the count the autoscaler set
        assert "replicas" not in deployments[name]["spec"], name
        assert autoscaler["spec"]["minReplicas"] >= 2
    budgets = of_kind(documents, "PodDisruptionBudget")
    for name, deployment in deployments.items():
        [budget] = [
            b for b in budgets.values() if selects(b["spec"]["selector"]["matchLabels"], deployment)
        ]
        scaler = autoscalers.get(name)
        least = scaler["spec"]["minReplicas"] if scaler else deployment["spec"]["replicas"]
        # a budget that leaves room for one eviction, so a node can still be drained
        assert budget["spec"]["minAvailable"] < least, name


def test_the_controllers_are_several(documents):
    assert of_kind(documents, "Deployment")["controller"]["spec"]["replicas"] >= 2


def test_every_secret_reference_names_a_key_of_the_generated_secret(documents):
    [secret] = of_kind(documents, "Secret").values()
    referenced = set()
    for _, container in containers(documents):
        for value in env_of(container).values():
            if isinstance(value, dict) and "secretKeyRef" in value:
                reference = value["secretKeyRef"]
                assert reference["name"] == secret["metadata"]["name"]
                referenced.add(reference["key"])
    assert referenced == set(secret["data"]), "a key of the Secret that nothing reads, or none"


def test_the_database_url_names_the_statefulset_and_its_user(rendered):
    documents = rendered[""]
    [secret] = of_kind(documents, "Secret").values()
    url = urlsplit(base64.b64decode(secret["data"]["database-url"]).decode())
    assert url.scheme == "postgresql"
    service = of_kind(documents, "Service")[url.hostname]
    assert service["spec"]["clusterIP"] == "None"
    assert [port["port"] for port in service["spec"]["ports"]] == [url.port]
    statefulset = of_kind(documents, "StatefulSet")["postgres"]
    assert statefulset["spec"]["serviceName"] == url.hostname
    assert selects(service["spec"]["selector"], statefulset)
    [postgres] = statefulset["spec"]["template"]["spec"]["containers"]
    env = env_of(postgres)
    assert (env["POSTGRES_USER"], env["POSTGRES_DB"]) == (url.username, url.path.lstrip("/"))
    assert statefulset["spec"]["volumeClaimTemplates"], "the database has no volume of its own"


def test_the_secrets_are_examples_only():
    for name in KUSTOMIZATIONS:
        example = env_file(K8S / name / f"{SECRETS}.example")
        assert example["service-token"] == "", f"deploy/k8s/{name} ships a service token"
        assert not example.get("postgres-password"), f"deploy/k8s/{name} ships a password"
        ignored = subprocess.run(
            ["git", "check-ignore", "-q", str(K8S / name / SECRETS)], cwd=ROOT, check=False
        )
        assert ignored.returncode == 0, f"git would take deploy/k8s/{name}/{SECRETS}"
