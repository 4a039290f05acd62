"""The page's plain modules, in process: the view store (kept views, renders, PNG answers) and the
page's files (media types, validators, gzip)."""

from __future__ import annotations

import cv2
import httpx
import numpy as np
import pytest
from starlette.applications import Starlette

from services.common.caches import ENTRY_OVERHEAD
from services.common.contracts.search import ViewSettings
from services.common.geometry.pose import GridIndex
from services.common.images import encode_ppm
from services.controller.page import INDEX, page_routes
from services.controller.views import ViewStore, displayable, to_png


def picture(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (24, 32, 3), dtype=np.uint8)


def rgb_of(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]


CURRENT = ViewSettings(spp=8)
SMALL = ViewSettings(spp=2, width=16)


@pytest.mark.anyio
async def test_a_view_rendered_once_is_kept_and_answered_as_png():
    asked: list[tuple[str, int, int, ViewSettings]] = []

    async def render(scene: str, index: GridIndex, settings: ViewSettings) -> bytes:
        asked.append((scene, index.lat, index.lon, settings))
        return encode_ppm(picture(index.lat * 100 + index.lon))

    views = ViewStore(render, max_bytes=10 << 20)
    first = await views.png("demo", GridIndex(lat=1, lon=2), CURRENT)
    assert np.array_equal(rgb_of(first), picture(102))
    assert await views.png("demo", GridIndex(lat=1, lon=2), CURRENT) == first
    assert (asked, views.renders, views.hits) == ([("demo", 1, 2, CURRENT)], 1, 1)

    views.remember("demo", GridIndex(lat=3, lon=4), CURRENT, encode_ppm(picture(7)))  # a search's
    assert np.array_equal(
        rgb_of(await views.png("demo", GridIndex(lat=3, lon=4), CURRENT)), picture(7)
    )
    assert len(asked) == 1  # not rendered: the search's own


@pytest.mark.anyio
async def test_views_of_one_pose_with_other_settings_are_other_views():
    asked: list[ViewSettings] = []

    async def render(scene: str, index: GridIndex, settings: ViewSettings) -> bytes:
        asked.append(settings)
        return encode_ppm(picture(settings.width or 0))

    views = ViewStore(render, max_bytes=10 << 20)
    pose = GridIndex(lat=1, lon=2)
    views.remember("demo", pose, CURRENT, encode_ppm(picture(1)))
    small = await views.png("demo", pose, SMALL)  # not the view kept: other pixels
    assert asked == [SMALL]
    assert np.array_equal(rgb_of(small), picture(16))
    assert np.array_equal(rgb_of(await views.png("demo", pose, CURRENT)), picture(1))
    assert await views.png("demo", pose, ViewSettings(spp=2, width=16)) == small  # equal settings
    assert (len(views), views.renders, views.hits) == (2, 1, 2)


@pytest.mark.anyio
async def test_the_view_store_is_bounded_by_bytes_least_recently_used_out():
    asked: list[tuple[int, int]] = []

    async def render(scene: str, index: GridIndex, settings: ViewSettings) -> bytes:
        asked.append((index.lat, index.lon))
        return to_png(encode_ppm(picture(index.lat * 100 + index.lon)))

    one = len(await render("demo", GridIndex(lat=0, lon=0), CURRENT)) + ENTRY_OVERHEAD
    asked.clear()
    views = ViewStore(render, max_bytes=int(2.5 * one))  # two views fit (the PNGs weigh ~alike)
    for lon in range(3):
        await views.png("demo", GridIndex(lat=1, lon=lon), CURRENT)
    assert len(views) == 2
    assert views.nbytes <= views.max_bytes
    await views.png("demo", GridIndex(lat=1, lon=2), CURRENT)  # kept
    await views.png("demo", GridIndex(lat=1, lon=0), CURRENT)  # the least recently used: gone
    assert asked == [(1, 0), (1, 1), (1, 2), (1, 0)]
    assert views.nbytes <= views.max_bytes

    nothing = ViewStore(render, max_bytes=0)  # keeps none: every view is rendered again
    png = await nothing.png("demo", GridIndex(lat=2, lon=2), CURRENT)
    assert await nothing.png("demo", GridIndex(lat=2, lon=2), CURRENT) == png
    assert (len(nothing), nothing.renders) == (0, 2)


def test_a_browser_gets_png_or_jpeg_never_ppm():
    ppm = encode_ppm(picture(3))
    png, media_type = displayable(ppm)
    assert media_type == "image/png"
    assert np.array_equal(rgb_of(png), picture(3))
    assert displayable(png) == (png, "image/png")
    jpeg = cv2.imencode(".jpg", picture(3))[1].tobytes()
    assert displayable(jpeg) == (jpeg, "image/jpeg")
    assert to_png(png) is png


def _page_client(directory) -> httpx.AsyncClient:
    transport = httpx.ASGITransport(Starlette(routes=page_routes(directory)))
    return httpx.AsyncClient(transport=transport, base_url="http://page")


@pytest.mark.anyio
async def test_the_page_files_have_media_types_validators_and_gzip(tmp_path):
    (tmp_path / "assets").mkdir()
    (tmp_path / INDEX).write_text("<!doctype html><p>" + "page " * 100)
    (tmp_path / "assets" / "app-ABC.js").write_text("export const x = 1;" * 100)
    (tmp_path / "assets" / "tiny-X.css").write_text("a{}")
    async with _page_client(tmp_path) as client:
        index = await client.get("/", headers={"Accept-Encoding": "identity"})
        assert index.headers["content-type"] == "text/html; charset=utf-8"
        assert index.headers["cache-control"] == "no-cache"
        assert "script-src 'self'" in index.headers["content-security-policy"]
        app = await client.get("/assets/app-ABC.js", headers={"Accept-Encoding": "gzip"})
        assert app.headers["content-type"] == "text/javascript; charset=utf-8"
        assert app.headers["cache-control"] == "public, max-age=31536000, immutable"
        assert app.headers["content-encoding"] == "gzip"
        assert app.text == "export const x = 1;" * 100  # inflated by the client
        assert app.num_bytes_downloaded < len(app.content)
        plain = await client.get("/assets/app-ABC.js", headers={"Accept-Encoding": "identity"})
        assert "content-encoding" not in plain.headers
        tiny = await client.get("/assets/tiny-X.css", headers={"Accept-Encoding": "gzip"})
        assert "content-encoding" not in tiny.headers  # gzip would make it larger
        for missing in ("/assets/nope.js", "/assets/..%2Findex.html"):
            assert (await client.get(missing)).status_code == 404


@pytest.mark.anyio
async def test_if_none_match(tmp_path):
    (tmp_path / INDEX).write_text("x")
    async with _page_client(tmp_path) as client:
        etag = (await client.get("/")).headers["etag"]
        for held in (etag, f'"other", W/{etag}'):
            again = await client.get("/", headers={"If-None-Match": held})
            assert again.status_code == 304
            assert again.content == b""
            assert again.headers["cache-control"] == "no-cache"
        other = await client.get("/", headers={"If-None-Match": '"other"'})
        assert other.status_code == 200
