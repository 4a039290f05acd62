"""The page's plain modules, in process: the view store (kept views, renders, PNG answers) and the
page's files (media types, validators, gzip)."""

from __future__ import annotations

import gzip

import cv2
import numpy as np
import pytest

from services.common.geometry.pose import GridIndex
from services.common.images import encode_ppm
from services.controller.page import INDEX, PageAssets, accepts_gzip, not_modified
from services.controller.views import ViewStore, displayable, to_png


def picture(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (24, 32, 3), dtype=np.uint8)


def rgb_of(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]


@pytest.mark.anyio
async def test_a_view_rendered_once_is_kept_and_answered_as_png():
    asked: list[tuple[str, int, int]] = []

    async def render(scene: str, index: GridIndex) -> bytes:
        asked.append((scene, index.lat, index.lon))
        return encode_ppm(picture(index.lat * 100 + index.lon))

    views = ViewStore(render, capacity=2)
    first = await views.png("demo", GridIndex(lat=1, lon=2))
    assert np.array_equal(rgb_of(first), picture(102))
    assert await views.png("demo", GridIndex(lat=1, lon=2)) == first
    assert (asked, views.renders, views.hits) == ([("demo", 1, 2)], 1, 1)

    views.remember("demo", GridIndex(lat=3, lon=4), encode_ppm(picture(7)))  # a search's view
    assert np.array_equal(rgb_of(await views.png("demo", GridIndex(lat=3, lon=4))), picture(7))
    assert len(asked) == 1  # not rendered: the search's own
    await views.png("garden", GridIndex(lat=1, lon=2))  # another scene, another view
    assert len(views) == 2  # the least recently used one went
    await views.png("demo", GridIndex(lat=1, lon=2))
    assert asked[-1] == ("demo", 1, 2)  # so it is rendered again
    with pytest.raises(ValueError, match="capacity"):
        ViewStore(render, capacity=0)


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
