"""A scene's own detector model, in process (ASGI transport, lifespan run) with real ONNX files.

Scene ``field`` is a copy of the demo scene (five balls: five classes, one per ball) whose model is
a copy of the shipped general model (five output classes) with a sidecar naming the balls: it
finds the same spheres, labelled with the balls' names. Onboarding is mimicked as ``cosmos scenes
add`` does it: the sidecar first, then the ONNX file renamed into place.
"""

from __future__ import annotations

import asyncio
import os
import shutil
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import httpx
import pytest
from asgi_lifespan import LifespanManager
from fastapi import FastAPI

from services.common.auth import bearer
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.scene_models import MODEL_DIR_SUFFIX, MODEL_FILE_NAME
from services.detector import registry as registry_module
from services.detector.app import create_app
from services.detector.detect import SCENE_CROSS_CLASS_IOU
from services.detector.registry import ModelRegistry
from services.detector.settings import DEFAULT_MODEL, DetectorSettings
from tests.scene_model_support import (
    BALLS,
    GENERAL_SIDECAR,
    add_scene,
    balls_png,
    blue_model,
    onboard,
    sha256,
)

pytestmark = pytest.mark.anyio

BUILTIN_MODELS = sorted(
    path.name.removesuffix(MODEL_DIR_SUFFIX)
    for path in BUILTIN_SCENES_DIR.glob(f"*{MODEL_DIR_SUFFIX}")
    if (path / MODEL_FILE_NAME).is_file()
)


IMAGE = balls_png()


@pytest.fixture
def scenes(tmp_path) -> Path:
    """A scenes directory with ``field`` (a demo copy) and its model onboarded, and ``plain``
    (another demo copy) without a model."""
    directory = tmp_path / "scenes"
    directory.mkdir()
    add_scene(directory, "field")
    onboard(directory, "field")
    add_scene(directory, "plain")
    return directory


@asynccontextmanager
async def serving(
    scenes: Path, check_s: float = 0.0
) -> AsyncIterator[tuple[httpx.AsyncClient, FastAPI]]:
    settings = DetectorSettings(
        scenes_dir=str(scenes), detector_threads=1, detector_scene_check_s=check_s
    )
    app = create_app(settings)
    async with LifespanManager(app) as manager:
        transport = httpx.ASGITransport(app=manager.app)
        headers = bearer(settings.token())  # as the controller calls it
        async with httpx.AsyncClient(
            transport=transport, base_url="http://detector", headers=headers
        ) as client:
            yield client, app


def registry_of(app: FastAPI) -> ModelRegistry:
    registry: ModelRegistry = app.state.detector.registry
    return registry


async def detect(client: httpx.AsyncClient, scene: str | None = None) -> dict:
    params = {} if scene is None else {"scene": scene}
    response = await client.post(
        "/detect", content=IMAGE, headers={"content-type": "image/png"}, params=params
    )
    assert response.status_code == 200, response.text
    return response.json()


def labels(body: dict) -> list[str]:
    return [d["label"] for d in body["detections"]]


async def scene_status(client: httpx.AsyncClient, scene_id: str) -> dict:
    response = await client.get("/models")
    assert response.status_code == 200, response.text
    (status,) = [s for s in response.json()["scenes"] if s["scene"] == scene_id]
    return status


# -- which model answers -----------------------------------------------------------------------


async def test_a_scene_with_its_own_model_is_detected_with_it(scenes):
    async with serving(scenes) as (client, app):
        body = await detect(client, "field")
        # one class per object: two classes on one box are one object (detect.py)
        own = registry_of(app)._entries["field"].detector
        assert own is not None
        assert own.options.cross_class_iou == SCENE_CROSS_CLASS_IOU
        assert body["model"]["scene"] == "field"
        assert body["model"]["classes"] == BALLS
        assert body["model"]["sha256"] == sha256(DEFAULT_MODEL)
        assert body["model"]["name"] == "field-detector"
        assert labels(body) == ["red", "red"]  # the general model's class 0 is the first ball


@pytest.mark.parametrize(
    "scene", [None, "plain", "no-such-scene"], ids=["none", "no-model", "unknown"]
)
async def test_otherwise_the_general_model_answers(scenes, scene):
    async with serving(scenes) as (client, _):
        body = await detect(client, scene)
        assert body["model"]["scene"] is None
        assert body["model"]["classes"] == GENERAL_SIDECAR["classes"]
        assert labels(body) == ["sphere", "sphere"]


async def test_a_malformed_scene_id_is_a_problem(scenes):
    async with serving(scenes) as (client, _):
        response = await client.post(
            "/detect",
            content=IMAGE,
            headers={"content-type": "image/png"},
            params={"scene": "../x"},
        )
        assert response.status_code == 422
        assert response.headers["content-type"] == "application/problem+json"
        assert response.json()["field"] == "scene"


async def test_models_health_and_model_list_what_serves(scenes):
    async with serving(scenes) as (client, _):
        body = (await client.get("/models")).json()
        assert body["general"] == (await client.get("/model")).json()
        assert body["general"]["scene"] is None
        by_scene = {s["scene"]: s for s in body["scenes"]}
        assert set(by_scene) == {"plain", "field", *BUILTIN_MODELS}
        field = by_scene["field"]
        assert (field["state"], field["error"], field["classes"]) == ("serving", None, 5)
        assert field["model"]["scene"] == "field"
        assert by_scene["plain"] == {
            "scene": "plain",
            "state": "none",
            "model": None,
            "error": None,
            "classes": 5,
        }
        health = (await client.get("/health")).json()
        assert health["scene_models"] == 1 + len(BUILTIN_MODELS)
        for built_in in BUILTIN_MODELS:  # the built-in scenes ship their own models
            assert by_scene[built_in]["state"] == "serving"


# -- picked up without a restart ---------------------------------------------------------------


async def test_a_replaced_model_is_picked_up_on_the_next_request(scenes, tmp_path):
    async with serving(scenes) as (client, app):
        first = registry_of(app)._entries["field"].detector
        assert labels(await detect(client, "field")) == ["red", "red"]
        assert registry_of(app)._entries["field"].detector is first  # unchanged: not reloaded
        new = blue_model(tmp_path)
        onboard(scenes, "field", new)
        body = await detect(client, "field")
        assert body["model"]["sha256"] == sha256(new)
        assert labels(body) == ["blue"]
        await asyncio.sleep(0.1)  # the old model retires once its requests are answered
        assert first is not None
        assert first.batcher._task is not None
        assert first.batcher._task.done()
        status = await scene_status(client, "field")
        assert (status["state"], status["model"]["sha256"]) == ("serving", sha256(new))


async def test_a_new_scene_and_its_model_are_picked_up(scenes):
    async with serving(scenes) as (client, _):
        assert (await detect(client, "meadow"))["model"]["scene"] is None
        add_scene(scenes, "meadow")
        assert (await detect(client, "meadow"))["model"]["scene"] is None  # no model yet
        onboard(scenes, "meadow")
        assert (await detect(client, "meadow"))["model"]["scene"] == "meadow"


async def test_a_new_model_is_found_by_the_listing_too(scenes):
    async with serving(scenes) as (client, _):
        assert (await scene_status(client, "plain"))["state"] == "none"
        add_scene(scenes, "meadow")
        onboard(scenes, "meadow")
        status = await scene_status(client, "meadow")
        assert (status["state"], status["model"]["scene"]) == ("serving", "meadow")


async def test_files_are_looked_at_at_most_once_per_interval(scenes, tmp_path):
    """Within the interval a request costs no look at the files, so a new model waits."""
    async with serving(scenes, check_s=3600) as (client, app):
        first = registry_of(app)._entries["field"].detector
        onboard(scenes, "field", blue_model(tmp_path))
        body = await detect(client, "field")
        assert (body["model"]["sha256"], labels(body)) == (sha256(DEFAULT_MODEL), ["red", "red"])
        assert registry_of(app)._entries["field"].detector is first


@pytest.mark.parametrize(("check_s", "rescans"), [(3600, 0), (0, 3)])
async def test_made_up_scene_ids_rescan_at_most_once_per_interval(
    scenes, check_s, rescans, monkeypatch
):
    async with serving(scenes, check_s=check_s) as (client, app):
        catalog = registry_of(app).catalog
        calls = []
        rescan = catalog.rescan
        monkeypatch.setattr(catalog, "rescan", lambda: (calls.append(1), rescan())[1])
        add_scene(scenes, "meadow")
        onboard(scenes, "meadow")
        for scene_id in ("made-up-1", "made-up-2", "meadow"):
            await detect(client, scene_id)
        assert len(calls) == rescans
        assert ((await detect(client, "meadow"))["model"]["scene"] == "meadow") == (check_s == 0)


async def test_a_load_does_not_hold_up_other_requests(scenes, tmp_path, monkeypatch):
    """While a new model loads (on a worker thread), the old one and the general one serve."""
    release = asyncio.Event()
    started = asyncio.Event()
    load = registry_module.load_scene_model
    loop = asyncio.get_running_loop()

    def slow_load(scene, *, threads):
        loop.call_soon_threadsafe(started.set)
        asyncio.run_coroutine_threadsafe(release.wait(), loop).result(timeout=30)
        return load(scene, threads=threads)

    async with serving(scenes) as (client, _):
        monkeypatch.setattr(registry_module, "load_scene_model", slow_load)
        new = blue_model(tmp_path)
        onboard(scenes, "field", new)
        finding = asyncio.create_task(detect(client, "field"))  # finds the change, waits
        await asyncio.wait_for(started.wait(), 30)
        meanwhile = await asyncio.gather(*(detect(client, "field") for _ in range(4)))
        assert {b["model"]["sha256"] for b in meanwhile} == {sha256(DEFAULT_MODEL)}
        assert (await detect(client))["model"]["scene"] is None
        assert not finding.done()
        release.set()
        assert (await finding)["model"]["sha256"] == sha256(new)


async def test_requests_under_way_when_a_model_is_replaced_are_answered(scenes, tmp_path):
    async with serving(scenes) as (client, _):
        new = blue_model(tmp_path)
        onboard(scenes, "field", new)
        answers = await asyncio.gather(*(detect(client, "field") for _ in range(12)))
        onboard(scenes, "field")
        answers += await asyncio.gather(*(detect(client, "field") for _ in range(12)))
        assert {b["model"]["sha256"] for b in answers} == {sha256(new), sha256(DEFAULT_MODEL)}
        assert (await detect(client, "field"))["model"]["sha256"] == sha256(DEFAULT_MODEL)


# -- refused models ----------------------------------------------------------------------------


def corrupt(scenes: Path, tmp_path: Path) -> str:
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"\x08\x07 not an onnx model" * 100)
    onboard(scenes, "field", bad)
    return "not a loadable ONNX model"


def sha_mismatch(scenes: Path, tmp_path: Path) -> str:
    onboard(scenes, "field", blue_model(tmp_path), sha="0" * 64)
    return "gives sha256 000000000000, the file's is"


def wrong_classes(scenes: Path, tmp_path: Path) -> str:
    onboard(scenes, "field", blue_model(tmp_path), classes=[*BALLS[1:], BALLS[0]])
    return "are not the object classes ['red', 'green', 'blue', 'yellow', 'magenta'] of scene"


def other_scene(scenes: Path, tmp_path: Path) -> str:
    onboard(scenes, "field", blue_model(tmp_path), scene="demo")
    return "is for scene 'demo', not 'field'"


def edited_scene(scenes: Path, tmp_path: Path) -> str:
    path = scenes / "field.yaml"
    path.write_text(path.read_text().replace("name: magenta", "name: purple"))
    return "was the scene file edited after onboarding?"


@pytest.mark.parametrize("damage", [corrupt, sha_mismatch, wrong_classes, other_scene])
async def test_a_refused_model_leaves_the_previous_one_serving(scenes, tmp_path, damage, caplog):
    async with serving(scenes) as (client, _):
        before = await scene_status(client, "field")
        expected = damage(scenes, tmp_path)
        body = await detect(client, "field")
        assert (body["model"]["sha256"], labels(body)) == (sha256(DEFAULT_MODEL), ["red", "red"])
        status = await scene_status(client, "field")
        assert status["state"] == "refused"
        assert expected in status["error"]
        assert status["model"] == before["model"]  # the previous model still serves
        assert expected in caplog.text  # logged, with what serves instead
        assert "its previous model" in caplog.text
        assert (await client.get("/health")).json()["scene_models"] == 1 + len(BUILTIN_MODELS)


async def test_a_scene_edited_after_onboarding_falls_back_to_the_general_model(
    scenes, tmp_path, caplog
):
    async with serving(scenes) as (client, _):
        expected = edited_scene(scenes, tmp_path)
        body = await detect(client, "field")
        # The old model's classes name a ball the scene no longer has: it must not serve.
        assert body["model"]["scene"] is None
        assert labels(body) == ["sphere", "sphere"]
        status = await scene_status(client, "field")
        assert (status["state"], status["model"]) == ("refused", None)
        assert expected in status["error"]
        assert "the general model serves it" in caplog.text


async def test_a_refused_model_with_none_before_leaves_the_general_one(scenes, tmp_path):
    async with serving(scenes) as (client, _):
        add_scene(scenes, "meadow")
        onboard(scenes, "meadow", blue_model(tmp_path), classes=["a", "b", "c", "d", "e"])
        assert (await detect(client, "meadow"))["model"]["scene"] is None
        status = await scene_status(client, "meadow")
        assert (status["state"], status["model"]) == ("refused", None)


async def test_a_half_written_model_is_not_loaded_until_its_file_is_in_place(scenes, tmp_path):
    new = blue_model(tmp_path)
    async with serving(scenes) as (client, _):
        onboard(scenes, "field", new, install=False)  # the sidecar is new, the file is not yet
        body = await detect(client, "field")
        assert body["model"]["sha256"] == sha256(DEFAULT_MODEL)
        assert "still being written" in (await scene_status(client, "field"))["error"]
        os.replace(
            shutil.copyfile(new, tmp_path / "staged.onnx"),
            scenes / "field.detector" / MODEL_FILE_NAME,
        )
        assert (await detect(client, "field"))["model"]["sha256"] == sha256(new)


async def test_a_scene_model_refused_at_start_up_does_not_stop_the_service(scenes, tmp_path):
    corrupt(scenes, tmp_path)
    async with serving(scenes) as (client, _):
        assert (await detect(client, "field"))["model"]["scene"] is None
        assert (await scene_status(client, "field"))["state"] == "refused"


async def test_a_removed_model_or_scene_stops_serving(scenes):
    async with serving(scenes) as (client, _):
        (scenes / "field.detector" / MODEL_FILE_NAME).unlink()
        assert (await detect(client, "field"))["model"]["scene"] is None
        assert (await scene_status(client, "field"))["state"] == "none"
        onboard(scenes, "field")
        assert (await detect(client, "field"))["model"]["scene"] == "field"
        (scenes / "field.yaml").unlink()
        assert (await detect(client, "field"))["model"]["scene"] is None
        scenes_listed = [s["scene"] for s in (await client.get("/models")).json()["scenes"]]
        assert "field" not in scenes_listed
