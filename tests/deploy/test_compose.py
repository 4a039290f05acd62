"""docker-compose.yml as `docker compose` would read it, without an engine: interpolated from
.env.example given values, valid against the Compose Specification's JSON schema (the copy
check-jsonschema ships), and sound: health checks everywhere, each service started once what it
calls is healthy, two controllers on one PostgreSQL behind the proxy's one published port, and
only settings the services read."""

from __future__ import annotations

import copy
import json
from importlib.resources import files
from typing import Any
from urllib.parse import urlsplit

import jsonschema
import pytest

from cosmos.environment import SERVICE_SETTINGS
from tests.deploy.compose import COMPOSE_ENV, load_compose
from tests.deploy.kustomize import env_file
from tests.deploy.manifests import IMAGE_SERVICES, containers, env_of


def compose_schema() -> dict[str, Any]:
    vendor = files("check_jsonschema.builtin_schemas.vendor")
    schema: dict[str, Any] = json.loads(vendor.joinpath("compose-spec.json").read_text())
    return schema


def spec_errors(data: dict[str, Any]) -> list[str]:
    schema = compose_schema()
    validator = jsonschema.validators.validator_for(schema)(schema)
    errors = validator.iter_errors(data)
    return [f"{'.'.join(map(str, error.path))}: {error.message}" for error in errors]


def stage_services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The services of the project's image, by the service each runs."""
    return {
        service["environment"]["SERVICE"]: service
        for service in compose["services"].values()
        if "SERVICE" in service.get("environment", {})
    }


def test_the_compose_file_follows_the_compose_specification(compose):
    assert spec_errors(compose) == []


def test_the_specification_refuses_a_misspelt_field(compose):
    broken = copy.deepcopy(compose)
    broken["services"]["renderer"]["healthchek"] = broken["services"]["renderer"].pop("healthcheck")
    assert any("healthchek" in error for error in spec_errors(broken))


def test_compose_stops_without_each_secret(compose_env):
    example = env_file(COMPOSE_ENV)
    assert set(example.values()) == {""}, ".env.example ships a secret"
    for name in example:
        with pytest.raises(KeyError, match=name):
            load_compose({**compose_env, name: ""})


def test_every_service_is_checked_for_health(compose):
    for name, service in compose["services"].items():
        test = " ".join(service["healthcheck"]["test"])
        if "SERVICE" in service.get("environment", {}):
            assert "/readyz" in test, name  # ready to serve, not only alive
    assert "pg_isready" in compose["services"]["postgres"]["healthcheck"]["test"]
    assert any("/livez" in part for part in compose["services"]["proxy"]["healthcheck"]["test"])


def test_each_service_starts_once_what_it_calls_is_healthy(compose):
    services = compose["services"]
    for name, service in services.items():
        for needed, condition in service.get("depends_on", {}).items():
            assert condition == {"condition": "service_healthy"}, f"{name} -> {needed}"
            assert "healthcheck" in services[needed], needed
    assert set(services["controller"]["depends_on"]) == {
        "renderer",
        "detector",
        "optimizer",
        "postgres",
    }
    assert set(services["proxy"]["depends_on"]) == {"controller"}


def test_two_controllers_are_published_on_one_port_through_the_proxy(compose):
    published = {name: s["ports"] for name, s in compose["services"].items() if "ports" in s}
    assert published == {"proxy": ["8000:8000"]}
    controller = compose["services"]["controller"]
    assert controller["deploy"]["replicas"] >= 2
    assert "container_name" not in controller  # which replicas would not allow


def test_the_controllers_share_the_postgres_service(compose, compose_env):
    services = compose["services"]
    url = urlsplit(services["controller"]["environment"]["COSMOS_CONTROLLER_DATABASE_URL"])
    assert url.scheme == "postgresql"
    assert (url.hostname, url.port) == ("postgres", 5432)
    postgres = services["postgres"]
    assert postgres["image"].startswith("postgres:")
    assert url.username == postgres["environment"]["POSTGRES_USER"]
    assert url.password == compose_env["POSTGRES_PASSWORD"]
    assert url.path == f"/{postgres['environment']['POSTGRES_DB']}"
    [volume] = postgres["volumes"]
    name, _, mount = volume.partition(":")
    assert name in compose["volumes"]
    assert mount == "/var/lib/postgresql/data"


def test_the_controllers_call_each_stage_by_its_service_name_and_port(compose):
    stages = stage_services(compose)
    controller = stages["controller"]["environment"]
    assert controller["COSMOS_CONTROLLER_DISCOVER_REPLICAS"] == "true"
    for stage in ("renderer", "detector", "optimizer"):
        [url] = controller[f"COSMOS_CONTROLLER_{stage.upper()}_URLS"].split(",")
        host, port = urlsplit(url).hostname, urlsplit(url).port
        assert compose["services"][host] is stages[stage]
        assert port == int(stages[stage]["environment"]["PORT"])


def test_every_cosmos_variable_is_one_its_service_reads(compose):
    stages = stage_services(compose)
    assert sorted(stages) == sorted(IMAGE_SERVICES)
    for name, service in stages.items():
        cosmos = {v for v in service["environment"] if v.startswith("COSMOS_")}
        reads = SERVICE_SETTINGS[name].variables()
        assert cosmos <= reads, f"{name} does not read {sorted(cosmos - reads)}"


def test_compose_and_kubernetes_give_each_service_the_same_settings(compose, rendered):
    stages = stage_services(compose)
    for workload, container in containers(rendered[""]):
        if workload["metadata"]["name"] == "postgres":
            continue
        in_k8s = env_of(container)
        in_compose = stages[in_k8s["SERVICE"]]["environment"]
        assert sorted(in_k8s) == sorted(in_compose), in_k8s["SERVICE"]
        for name, value in in_k8s.items():
            if isinstance(value, str):  # not a secret
                assert in_compose[name] == value, name
