"""The proxy of `docker compose up` (deploy/proxy/nginx.conf), read with crossplane (NGINX's
own parser, strict: unknown directives, wrong contexts and argument counts are errors) inside
an http block, as the nginx image includes it: every request goes to the controllers, their
event streams pass unbuffered, and the controller, not nginx, answers an oversized upload."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import crossplane
import pytest
from sse_starlette import EventSourceResponse

from services.controller.settings import ControllerSettings
from tests.support import ROOT

CONFIG = ROOT / "deploy" / "proxy" / "nginx.conf"
MOUNTED_AT = "/etc/nginx/conf.d/default.conf"
"""Where the nginx image includes site configurations from, inside its http block."""

Directive = dict[str, Any]
SECONDS = {"ms": 0.001, "s": 1, "m": 60, "h": 3600, "d": 86400}
BYTES = {"k": 1024, "m": 1024**2, "g": 1024**3}


def parse(config: Path, tmp_path: Path) -> dict[str, Any]:
    wrapper = tmp_path / "nginx.conf"
    wrapper.write_text(f"events {{}}\nhttp {{\n    include {config};\n}}\n")
    parsed: dict[str, Any] = crossplane.parse(
        str(wrapper), check_ctx=True, check_args=True, strict=True
    )
    return parsed


def directives(block: list[Directive], name: str) -> list[Directive]:
    return [directive for directive in block if directive["directive"] == name]


def one(block: list[Directive], name: str) -> list[str]:
    [directive] = directives(block, name)
    args: list[str] = directive["args"]
    return args


def seconds(value: str) -> float:
    match = re.fullmatch(r"(\d+)(ms|s|m|h|d)?", value)
    assert match, value
    return int(match.group(1)) * SECONDS[match.group(2) or "s"]


@pytest.fixture
def http(tmp_path: Path) -> list[Directive]:
    """The directives of deploy/proxy/nginx.conf, as nginx reads them in its http block."""
    parsed = parse(CONFIG, tmp_path)
    assert parsed["status"] == "ok", parsed["errors"]
    [included] = [c for c in parsed["config"] if c["file"] == str(CONFIG)]
    block: list[Directive] = included["parsed"]
    return block


def location(http: list[Directive]) -> list[Directive]:
    [server] = directives(http, "server")
    [root] = [d for d in directives(server["block"], "location") if d["args"] == ["/"]]
    block: list[Directive] = root["block"]
    return block


def test_the_parser_refuses_a_misspelt_directive(tmp_path: Path):
    broken = tmp_path / "broken.conf"
    broken.write_text(CONFIG.read_text().replace("proxy_buffering off", "proxy_bufering off"))
    parsed = parse(broken, tmp_path)
    assert parsed["status"] == "failed"
    assert "proxy_bufering" in parsed["errors"][0]["error"]


def test_compose_mounts_the_config_where_nginx_includes_it(compose):
    proxy = compose["services"]["proxy"]
    assert proxy["image"].startswith("nginx:")
    [volume] = proxy["volumes"]
    source, target, mode = volume.split(":")
    assert (ROOT / source).resolve() == CONFIG
    assert (target, mode) == (MOUNTED_AT, "ro")


def test_every_request_goes_to_every_controller(http, compose):
    [server] = directives(http, "server")
    published = compose["services"]["proxy"]["ports"][0].split(":")[-1]
    assert [d["args"] for d in directives(server["block"], "listen")] == [[published]]
    assert one(location(http), "proxy_pass") == ["http://controllers"]
    [upstream] = [d for d in directives(http, "upstream") if d["args"] == ["controllers"]]
    [(address, *options)] = [d["args"] for d in directives(upstream["block"], "server")]
    host, port = address.split(":")
    controller = compose["services"][host]
    assert port == controller["environment"]["PORT"]
    # a controller replica started or replaced is followed through DNS, without a reload
    assert "resolve" in options
    assert directives(upstream["block"], "zone")
    assert directives(http, "resolver")


def test_event_streams_pass_unbuffered_and_stay_open(http):
    block = location(http)
    assert one(block, "proxy_buffering") == ["off"]
    assert one(block, "proxy_cache") == ["off"]
    # keep-alive (an upstream connection reused) needs HTTP/1.1 and no "Connection: close"
    assert one(block, "proxy_http_version") == ["1.1"]
    headers = {tuple(d["args"]) for d in directives(block, "proxy_set_header")}
    assert ("Connection", "") in headers
    # a quiet stream still sends a comment every ping interval: well within the read timeout
    [read_timeout] = one(block, "proxy_read_timeout")
    assert seconds(read_timeout) >= 4 * EventSourceResponse.DEFAULT_PING_INTERVAL


def test_the_controller_not_nginx_refuses_an_oversized_upload(http):
    [server] = directives(http, "server")
    [limit] = one(server["block"], "client_max_body_size")
    match = re.fullmatch(r"(\d+)([kmg])", limit.lower())
    assert match
    upload_limit = ControllerSettings.model_fields["controller_max_upload_bytes"].default
    assert int(match.group(1)) * BYTES[match.group(2)] > upload_limit
    assert one(location(http), "proxy_request_buffering") == ["off"]
