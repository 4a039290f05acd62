"""The page's plain modules, in process: the view store (kept views, renders, PNG answers) and the
page's files (media types, validators, gzip)."""

from __future__ import annotations

import gzip

import cv2
import numpy as np
import pytest

from services.common.caches import ENTRY_OVERHEAD
from services.common.contracts.search import ViewSettings
from services.common.geometry.pose import GridIndex
from services.common.images import encode_ppm
from services.controller.page import INDEX, PageAssets, accepts_gzip, not_modified
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


def test_the_page_files_have_media_types_validators_and_gzip(tmp_path):
    (tmp_path / "assets").mkdir()
    (tmp_path / INDEX).write_text("<!doctype html><p>" + "page " * 100)
    (tmp_path / "assets" / "app-ABC.js").write_text("export const x = 1;" * 100)
    (tmp_path / "assets" / "tiny-X.css").write_text("a{}")
    page = PageAssets(tmp_path)
    assert page.index is not None
    assert page.index.media_type == "text/html; charset=utf-8"
    assert page.index.cache_control == "no-cache"
    app = page.asset("app-ABC.js")
    assert app is not None
    assert app.media_type == "text/javascript; charset=utf-8"
    assert app.cache_control == "public, max-age=31536000, immutable"
    assert app.gzipped is not None
    assert gzip.decompress(app.gzipped) == app.body
    assert app.headers(gzip_ok=True)["Content-Encoding"] == "gzip"
    assert "Content-Encoding" not in app.headers(gzip_ok=False)
    tiny = page.asset("tiny-X.css")
    assert tiny is not None
    assert tiny.gzipped is None  # gzip would make it larger
    assert page.asset("nope.js") is None
    assert page.asset("../index.html") is None
    assert PageAssets(tmp_path / "unbuilt").index is None


@pytest.mark.parametrize(
    ("header", "gzip_ok"),
    [
        ("gzip, deflate, br", True),
        ("br;q=1.0, gzip;q=0.5", True),
        ("gzip;q=0", False),
        ("identity", False),
        ("", False),
        ("*", True),
    ],
)
def test_accept_encoding(header, gzip_ok):
    assert accepts_gzip(header) is gzip_ok


def test_if_none_match(tmp_path):
    (tmp_path / INDEX).write_text("x")
    index = PageAssets(tmp_path).index
    assert index is not None
    assert not_modified(index, index.etag)
    assert not_modified(index, f'"other", W/{index.etag}')
    assert not_modified(index, "*")
    assert not not_modified(index, '"other"')
    assert not not_modified(index, "")
