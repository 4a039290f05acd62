"""Each service reads its own variables: the renderer's default spp and body limit, the
controller's search-view spp and the optimizer's body limit have one name each, and the old
shared names still work for one release, with a warning naming the new one."""

from __future__ import annotations

import logging

import pytest

from services.controller.settings import ControllerSettings
from services.optimizer.settings import OptimizerSettings
from services.renderer.settings import RendererSettings

DEFAULTS = {
    (RendererSettings, "renderer_default_spp"): 16,
    (RendererSettings, "renderer_max_body_bytes"): 64 * 1024,
    (ControllerSettings, "controller_view_spp"): 8,
    (OptimizerSettings, "optimizer_max_body_bytes"): 2 * 1024 * 1024,
}


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in (
        "COSMOS_RENDER_SPP",
        "COSMOS_MAX_BODY_BYTES",
        *(f"COSMOS_{field.upper()}" for _, field in DEFAULTS),
    ):
        monkeypatch.delenv(name, raising=False)


@pytest.mark.parametrize(("settings", "field"), list(DEFAULTS))
def test_each_service_reads_only_its_own_variable(monkeypatch, settings, field):
    monkeypatch.setenv(f"COSMOS_{field.upper()}", "1024")
    for (other, other_field), default in DEFAULTS.items():
        expected = 1024 if (other, other_field) == (settings, field) else default
        assert getattr(other(), other_field) == expected, (other.__name__, other_field)


@pytest.mark.parametrize(
    ("old", "readers"),
    [
        (
            "COSMOS_RENDER_SPP",
            [
                (RendererSettings, "renderer_default_spp"),
                (ControllerSettings, "controller_view_spp"),
            ],
        ),
        (
            "COSMOS_MAX_BODY_BYTES",
            [
                (RendererSettings, "renderer_max_body_bytes"),
                (OptimizerSettings, "optimizer_max_body_bytes"),
            ],
        ),
    ],
)
def test_an_old_shared_name_still_works_with_a_warning(monkeypatch, caplog, old, readers):
    monkeypatch.setenv(old, "1024")
    for settings, field in readers:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="services.common.settings"):
            assert getattr(settings(), field) == 1024
        [message] = caplog.messages
        assert old in message
        assert f"set COSMOS_{field.upper()} instead" in message
        assert "different things to different services" in message


def test_a_new_name_wins_over_the_old_one(monkeypatch, caplog):
    monkeypatch.setenv("COSMOS_RENDER_SPP", "3")
    monkeypatch.setenv("COSMOS_CONTROLLER_VIEW_SPP", "5")
    with caplog.at_level(logging.WARNING, logger="services.common.settings"):
        assert ControllerSettings().controller_view_spp == 5
    assert caplog.messages == [
        "COSMOS_RENDER_SPP is ignored: COSMOS_CONTROLLER_VIEW_SPP is set. Unset COSMOS_RENDER_SPP."
    ]


def test_settings_given_in_code_win_over_the_environment(monkeypatch):
    monkeypatch.setenv("COSMOS_RENDER_SPP", "3")
    assert RendererSettings(renderer_default_spp=7).renderer_default_spp == 7
