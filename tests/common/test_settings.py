"""Each service reads its own ``COSMOS_<SERVICE>_`` variables (and the shared
``COSMOS_SCENES_DIR``, ``COSMOS_SERVICE_TOKEN`` and ``COSMOS_SERVICE_AUTH``); a ``COSMOS_``
variable that nothing reads is reported at start-up, with the likeliest name meant, and one
under another service's prefix is left to that service."""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from cosmos import cli
from cosmos.cli import up
from cosmos.environment import READERS, SERVICE_SETTINGS, SHARED, unknown_variables
from cosmos.stack import plan_stack
from services.common.settings import CLIENT_VARIABLES, SERVICE_PREFIXES
from services.common.settings import unknown_variables as service_unknown_variables
from services.controller.app import create_app as create_controller
from services.controller.broker import Heuristic
from services.detector.app import create_app as create_detector
from services.optimizer.app import create_app as create_optimizer
from services.renderer.app import create_app as create_renderer
from services.renderer.settings import RendererSettings

SAMPLES: dict[str, tuple[str, Any]] = {
    "COSMOS_SCENES_DIR": ("/srv/scenes", "/srv/scenes"),
    "COSMOS_SERVICE_TOKEN": ("t" * 32, SecretStr("t" * 32)),
    "COSMOS_SERVICE_AUTH": ("off", "off"),
    "COSMOS_RENDERER_MITSUBA_VARIANT": ("scalar_rgb", "scalar_rgb"),
    "COSMOS_RENDERER_DEFAULT_SPP": ("32", 32),
    "COSMOS_RENDERER_MAX_SPP": ("128", 128),
    "COSMOS_RENDERER_MAX_SIDE": ("1024", 1024),
    "COSMOS_RENDERER_MAX_PIXELS": ("1000000", 1_000_000),
    "COSMOS_RENDERER_MAX_SAMPLES": ("4096", 4096),
    "COSMOS_RENDERER_MAX_QUEUE": ("4", 4),
    "COSMOS_RENDERER_SLICE_SAMPLES": ("65536", 65536),
    "COSMOS_RENDERER_SCENE_CACHE": ("2", 2),
    "COSMOS_RENDERER_MAX_BODY_BYTES": ("4096", 4096),
    "COSMOS_DETECTOR_MODEL": ("/srv/m.onnx", Path("/srv/m.onnx")),
    "COSMOS_DETECTOR_SCENE_CHECK_S": ("5", 5.0),
    "COSMOS_DETECTOR_CONF": ("0.4", 0.4),
    "COSMOS_DETECTOR_IOU": ("0.6", 0.6),
    "COSMOS_DETECTOR_MAX_DETECTIONS": ("10", 10),
    "COSMOS_DETECTOR_MAX_CANDIDATES": ("100", 100),
    "COSMOS_DETECTOR_THREADS": ("1", 1),
    "COSMOS_DETECTOR_MAX_BATCH": ("2", 2),
    "COSMOS_DETECTOR_TILES": ("3", 3),
    "COSMOS_DETECTOR_BATCH_WINDOW_MS": ("1.5", 1.5),
    "COSMOS_DETECTOR_MAX_IN_FLIGHT": ("8", 8),
    "COSMOS_DETECTOR_MAX_DECODE_BYTES": ("200000000", 200_000_000),
    "COSMOS_DETECTOR_DECODE_WAIT_S": ("0.5", 0.5),
    "COSMOS_DETECTOR_MAX_UPLOAD_BYTES": ("4096", 4096),
    "COSMOS_DETECTOR_BODY_BUDGET_BYTES": ("104857600", 104857600),
    "COSMOS_DETECTOR_BODY_WAIT_S": ("0.5", 0.5),
    "COSMOS_DETECTOR_BODY_TIMEOUT_S": ("3", 3.0),
    "COSMOS_DETECTOR_BODY_MIN_BYTES_PER_S": ("65536", 65536.0),
    "COSMOS_DETECTOR_MAX_IMAGE_PIXELS": ("10000", 10_000),
    "COSMOS_DETECTOR_MAX_IMAGE_SIDE": ("100", 100),
    "COSMOS_DETECTOR_COLOUR": ("false", False),
    "COSMOS_OPTIMIZER_DEFAULT_STRATEGY": ("paper", "paper"),
    "COSMOS_OPTIMIZER_PAPER_CALIBRATION": ("/srv/c.json", Path("/srv/c.json")),
    "COSMOS_OPTIMIZER_MAX_GRID_POSES": ("500", 500),
    "COSMOS_OPTIMIZER_MAX_HISTORY_DETECTIONS": ("50", 50),
    "COSMOS_OPTIMIZER_MAX_BODY_BYTES": ("4096", 4096),
    "COSMOS_OPTIMIZER_MAX_IMAGE_PIXELS": ("10000", 10_000),
    "COSMOS_OPTIMIZER_MAX_IMAGE_SIDE": ("100", 100),
    "COSMOS_OPTIMIZER_TARGET_CACHE_BYTES": ("0", 0),
    "COSMOS_CONTROLLER_RENDERER_URLS": ("http://r:1", "http://r:1"),
    "COSMOS_CONTROLLER_DETECTOR_URLS": ("http://d:1", "http://d:1"),
    "COSMOS_CONTROLLER_OPTIMIZER_URLS": ("http://o:1", "http://o:1"),
    "COSMOS_CONTROLLER_DATABASE_URL": ("sqlite:///srv/c.db", "sqlite:///srv/c.db"),
    "COSMOS_CONTROLLER_LEASE_S": ("4.5", 4.5),
    "COSMOS_CONTROLLER_BROKER_HEURISTIC": ("round-robin", Heuristic.ROUND_ROBIN),
    "COSMOS_CONTROLLER_DISCOVER_REPLICAS": ("true", True),
    "COSMOS_CONTROLLER_DISCOVERY_INTERVAL_S": ("3", 3.0),
    "COSMOS_CONTROLLER_MAX_CONCURRENT_SEARCHES": ("2", 2),
    "COSMOS_CONTROLLER_DEFAULT_MAX_ITERATIONS": ("20", 20),
    "COSMOS_CONTROLLER_VIEW_SPP": ("4", 4),
    "COSMOS_CONTROLLER_VIEW_WIDTH": ("160", 160),
    "COSMOS_CONTROLLER_VIEW_CACHE_BYTES": ("1048576", 1048576),
    "COSMOS_CONTROLLER_RENDER_TIMEOUT_S": ("5", 5.0),
    "COSMOS_CONTROLLER_DETECT_TIMEOUT_S": ("6", 6.0),
    "COSMOS_CONTROLLER_OPTIMIZE_TIMEOUT_S": ("7", 7.0),
    "COSMOS_CONTROLLER_CONNECT_TIMEOUT_S": ("1.5", 1.5),
    "COSMOS_CONTROLLER_OUTAGE_BUDGET_S": ("0", 0.0),
    "COSMOS_CONTROLLER_MAX_UPLOAD_BYTES": ("4096", 4096),
    "COSMOS_CONTROLLER_BODY_BUDGET_BYTES": ("104857600", 104857600),
    "COSMOS_CONTROLLER_BODY_WAIT_S": ("0.5", 0.5),
    "COSMOS_CONTROLLER_BODY_TIMEOUT_S": ("3", 3.0),
    "COSMOS_CONTROLLER_BODY_MIN_BYTES_PER_S": ("65536", 65536.0),
    "COSMOS_CONTROLLER_MAX_IMAGE_PIXELS": ("10000", 10_000),
    "COSMOS_CONTROLLER_MAX_IMAGE_SIDE": ("100", 100),
    "COSMOS_CONTROLLER_AUTH": ("off", False),
    "COSMOS_CONTROLLER_CORS_ORIGINS": ("https://a.example", "https://a.example"),
    "COSMOS_CONTROLLER_QUOTA_ACTIVE_SEARCHES": ("3", 3),
    "COSMOS_CONTROLLER_QUOTA_SEARCHES_PER_MINUTE": ("5", 5),
    "COSMOS_CONTROLLER_QUOTA_STORED_BYTES": ("4096", 4096),
    "COSMOS_CONTROLLER_RETENTION_S": ("60", 60.0),
    "COSMOS_CONTROLLER_RETENTION_SWEEP_S": ("5", 5.0),
}
"""A valid value of every variable a service reads, other than its default, and what it reads as."""

APPS = {
    "renderer": create_renderer,
    "detector": create_detector,
    "optimizer": create_optimizer,
    "controller": create_controller,
}
SETTINGS_LOG = "services.common.settings"
ROOT = Path(__file__).resolve().parents[2]


def field(variable: str) -> str:
    return variable.removeprefix("COSMOS_").lower()


def readers(variable: str) -> list[type[Any]]:
    return [SERVICE_SETTINGS[service] for service in READERS[variable]]


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("COSMOS_"):
            monkeypatch.delenv(name)


def test_every_variable_a_service_reads_has_a_sample():
    services = {name for name in READERS if name not in CLIENT_VARIABLES}
    assert set(SAMPLES) == services
    for name, (_, expected) in SAMPLES.items():
        for settings in readers(name):
            assert getattr(settings(), field(name)) != expected, f"{name}: sample is the default"


@pytest.mark.parametrize("name", list(SAMPLES))
def test_each_variable_is_read_by_its_services_only(monkeypatch, name):
    defaults = {service: settings().model_dump() for service, settings in SERVICE_SETTINGS.items()}
    value, expected = SAMPLES[name]
    monkeypatch.setenv(name, value)
    for service, settings in SERVICE_SETTINGS.items():
        read = settings().model_dump()
        if service in READERS[name]:
            assert read[field(name)] == expected
            assert read == {**defaults[service], field(name): expected}
        else:
            assert read == defaults[service], f"{service} reads {name}"


def test_a_service_reads_its_own_prefix_and_the_shared_variables_only():
    assert set(SERVICE_PREFIXES) == set(SERVICE_SETTINGS)
    for service, settings in SERVICE_SETTINGS.items():
        prefix = SERVICE_PREFIXES[service]
        assert settings.variables(), service
        for name in settings.variables():
            assert name.startswith(prefix) or name in SHARED, name
    for name, who in READERS.items():
        assert len(who) == 1 or name in SHARED, f"{name} is read by {who}"


def test_settings_given_in_code_win_over_the_environment(monkeypatch):
    monkeypatch.setenv("COSMOS_RENDERER_DEFAULT_SPP", "5")
    assert RendererSettings(renderer_default_spp=7).renderer_default_spp == 7


TYPOS = {
    "renderer": ("COSMOS_RENDERER_DEFALT_SPP", "COSMOS_RENDERER_DEFAULT_SPP"),
    "detector": ("COSMOS_DETECTOR_CONFF", "COSMOS_DETECTOR_CONF"),
    "optimizer": ("COSMOS_OPTIMIZER_DEFALT_STRATEGY", "COSMOS_OPTIMIZER_DEFAULT_STRATEGY"),
    "controller": ("COSMOS_CONTROLLER_DATABSE_URL", "COSMOS_CONTROLLER_DATABASE_URL"),
}
"""A typo of one of each service's variables, and the variable meant."""


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize("service", APPS)
def test_an_unknown_variable_is_reported_at_start_up(monkeypatch, caplog, service):
    typo, meant = TYPOS[service]
    monkeypatch.setenv(typo, "32")
    monkeypatch.setenv("COSMOS_NOBODY", "1")
    with caplog.at_level(logging.WARNING, logger=SETTINGS_LOG):
        APPS[service]()
    assert [(r.name, r.levelno) for r in caplog.records] == [(SETTINGS_LOG, logging.WARNING)] * 2
    nobody, mistyped = sorted(caplog.messages, key=lambda m: not m.startswith("COSMOS_NOBODY"))
    assert nobody.startswith("COSMOS_NOBODY is ignored: no COSMOS 3D Search service reads it.")
    assert mistyped.startswith(
        f"{typo} is ignored: no COSMOS 3D Search service reads it (did you mean {meant}?)."
    )


@pytest.mark.parametrize("service", APPS)
def test_a_mistyped_service_prefix_is_reported_with_the_name_meant(monkeypatch, caplog, service):
    monkeypatch.setenv("COSMOS_RENDRER_MAX_SPP", "32")
    with caplog.at_level(logging.WARNING, logger=SETTINGS_LOG):
        APPS[service]()
    [message] = _warnings(caplog)
    assert message.startswith(
        "COSMOS_RENDRER_MAX_SPP is ignored: no COSMOS 3D Search service reads it "
        "(did you mean COSMOS_RENDERER_MAX_SPP?)."
    )


@pytest.mark.parametrize(
    "old", ["COSMOS_RENDER_SPP", "COSMOS_DATABASE_URL", "COSMOS_MAX_BODY_BYTES"]
)
def test_the_old_names_of_the_last_release_are_unknown_now(monkeypatch, old):
    monkeypatch.setenv(old, "8")
    assert unknown_variables() == [old]


@pytest.mark.parametrize("service", APPS)
def test_another_services_variable_is_not_reported(monkeypatch, caplog, service):
    others = {name for name, who in READERS.items() if service not in who}
    assert {"COSMOS_TRAINING", "COSMOS_API_KEY"} < others
    for name in others:
        monkeypatch.setenv(name, SAMPLES.get(name, ("1",))[0])
    # under another service's prefix, even a typo is that service's to report
    others_typos = [typo for other, (typo, _) in TYPOS.items() if other != service]
    for typo in others_typos:
        monkeypatch.setenv(typo, "1")
    with caplog.at_level(logging.DEBUG):
        APPS[service]()
    assert _warnings(caplog) == []


def test_the_operator_reports_what_a_service_leaves_to_another():
    environ = {"COSMOS_DETECTOR_CONFF": "0.3", "COSMOS_RENDERER_MAX_SPP": "8"}
    assert service_unknown_variables([RendererSettings], environ) == []
    assert unknown_variables(environ) == ["COSMOS_DETECTOR_CONFF"]


def test_cosmos_up_reports_an_unknown_variable_on_its_terminal(monkeypatch, caplog, tmp_path):
    def no_stack(*args: object, **kwargs: object) -> None:
        raise RuntimeError("not starting services in this test")

    monkeypatch.setattr(up, "running_stack", no_stack)
    monkeypatch.setenv("COSMOS_NOBODY", "1")
    # cosmos up makes its local key before it starts anything: not in the repository's data/
    monkeypatch.setenv("COSMOS_CONTROLLER_DATABASE_URL", f"sqlite:///{tmp_path}/c.sqlite3")
    with caplog.at_level(logging.WARNING, logger=SETTINGS_LOG):
        assert cli.main(["up"]) == 1
    [message] = caplog.messages
    assert message.startswith("COSMOS_NOBODY is ignored")


def test_names_are_matched_as_the_settings_read_them_regardless_of_case():
    environ = {"cosmos_detector_conf": "0.3", "cosmos_nobody": "1", "PATH": "/bin"}
    assert unknown_variables(environ) == ["COSMOS_NOBODY"]


def test_the_stack_and_the_containers_use_current_names_only():
    plan = plan_stack(database_url="sqlite:///x.db", env={})
    names = {name for service in plan for name in service.env}
    for path in ("docker-compose.yml", "Dockerfile"):
        names |= set(re.findall(r"\bCOSMOS_[A-Z_]+\b", (ROOT / path).read_text()))
    assert "COSMOS_CONTROLLER_RENDERER_URLS" in names
    assert names <= set(READERS), names - set(READERS)
