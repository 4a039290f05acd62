"""The page's fixtures: the real stack (four processes on loopback, as ``cosmos up`` runs them),
Debian's Chromium driven by Playwright, and a browser page that holds the stack's API key.

Chromium is ``/usr/bin/chromium`` (``scripts/bootstrap.sh`` installs the Debian package; here it
is installed too when missing and this user may). No browser is downloaded. The tests skip only
when Chromium truly cannot be had; on CI (``CI`` set) they fail instead.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from cosmos.stack import Stack, local_stack
from services.common.contracts.render import RenderRequest
from services.common.geometry.pose import PoseQuery
from services.renderer.client import RendererClient

CHROMIUM = Path("/usr/bin/chromium")
# The README's screenshots are rewritten only when asked (SCREENSHOTS_DIR=docs/screenshots), so a
# test run leaves the working tree as it found it; otherwise they go to a temporary folder.
SCREENSHOTS = Path(os.environ.get("SCREENSHOTS_DIR") or tempfile.mkdtemp(prefix="cosmos-shots-"))
# SwiftShader: WebGL without a GPU (headless Chromium refuses the software fallback otherwise)
CHROMIUM_ARGS = ["--enable-unsafe-swiftshader", "--use-angle=swiftshader"]


def _install_chromium() -> str | None:
    """Install Debian's ``chromium`` if missing; None when it is there, else why not."""
    if CHROMIUM.exists():
        return None
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return f"{CHROMIUM} is missing and this user cannot apt-get install chromium (not root)"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-qq", "chromium"]
    for step in (install, ["apt-get", "update", "-qq"], install):
        subprocess.run(step, env=env, capture_output=True, timeout=900, check=False)
        if CHROMIUM.exists():
            return None
    return "apt-get install chromium failed (see scripts/bootstrap.sh)"


@pytest.fixture(scope="session")
def chromium() -> str:
    why = _install_chromium()
    if why is not None:
        if os.environ.get("CI"):
            pytest.fail(f"the browser tests must run on CI: {why}")
        pytest.skip(why)
    return str(CHROMIUM)


@pytest.fixture(scope="session")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with local_stack(tmp_path_factory.mktemp("page-stack")) as running:
        yield running


@pytest.fixture(scope="module")
def browser(chromium: str):
    """Chromium for one test module. Playwright's sync API runs an event loop in this thread
    while it is open, and anyio's async tests cannot run beside it: it is closed with the
    module that used it."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        yield launched
        launched.close()


class PageErrors(list):
    """The page's uncaught errors (a test that sees one fails)."""


@pytest.fixture
def page(browser, stack: Stack):
    """A fresh browser tab on the stack's controller that holds the API key, as a user's does
    after giving it once; its uncaught errors must stay none."""
    context = browser.new_context(viewport={"width": 1280, "height": 1000})
    context.add_init_script(f"localStorage.setItem('cosmos.apiKey', {json.dumps(stack.api_key)})")
    tab = context.new_page()
    errors = PageErrors()
    tab.on("pageerror", lambda error: errors.append(str(error)))
    tab.errors = errors
    yield tab
    context.close()
    assert not errors, errors


def render_png(stack: Stack, scene: str, lat: int, lon: int, **film) -> bytes:
    """A target rendered by the stack's renderer (with its service token)."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as client:
        return client.render_png(
            RenderRequest(scene=scene, pose=PoseQuery(lat=lat, lon=lon), **film)
        )


def api(stack: Stack) -> httpx.Client:
    """An HTTP client of the stack's controller, with its API key."""
    return httpx.Client(
        base_url=stack.controller,
        headers={"Authorization": f"Bearer {stack.api_key}"},
        timeout=60.0,
    )
