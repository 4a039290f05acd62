"""Tiled detection of large photos: the tile geometry, the merge, and the real models on real
renders of a wide drone view whose objects are a dozen input pixels across."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from cosmos.bench.free_targets.rendering import LocalRenderer
from services.common.catalog import SceneCatalog
from services.common.contracts.detect import DetectResponse
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.geometry.free_camera import FreeCamera
from services.detector.detect import Detector
from services.detector.postprocess import Candidates, box_iou
from services.detector.registry import load_scene_model
from services.detector.settings import DetectorSettings
from services.detector.tiles import MIN_SHRINK, OVERLAP, merged, tile_grid, wants_tiles
from services.renderer.engine import RenderEngine
from services.renderer.imaging import encode_png

# -- geometry and merge ------------------------------------------------------------------------


def test_tiles_cover_the_image_and_overlap():
    tiles = tile_grid((1280, 960), 2)
    assert tiles == [
        (0, 0, 800, 600),
        (480, 0, 1280, 600),
        (0, 360, 800, 960),
        (480, 360, 1280, 960),
    ]
    for n in (2, 3, 4):
        grid = tile_grid((4000, 3000), n)
        assert len(grid) == n * n
        covered = np.zeros((3000, 4000), dtype=bool)
        for x0, y0, x1, y1 in grid:
            assert (x1 - x0) == pytest.approx(4000 * (1 + OVERLAP) / n, abs=1)
            covered[y0:y1, x0:x1] = True
        assert covered.all()


def test_only_an_image_twice_the_input_is_tiled():
    assert wants_tiles((1280, 960), (320, 256), 2)
    assert not wants_tiles((320, 240), (320, 256), 2)  # a search's view: the input's own size
    assert not wants_tiles((1280, 500), (320, 256), 2)  # under twice the input's height
    assert not wants_tiles((1280, 960), (320, 256), 1)
    assert not wants_tiles((1280, 960), (320, 256), 0)
    assert MIN_SHRINK == 2.0


def _candidates(rows: list[tuple[float, float, float, float, float, int]]) -> Candidates:
    a = np.array(rows, dtype=np.float64).reshape(-1, 6)
    return Candidates(a[:, :4], a[:, 4], a[:, 5].astype(np.int64))


def test_the_merge_trusts_a_tile_for_small_objects_and_the_whole_image_for_large_ones():
    size, gain = (1000, 1000), 0.32  # a 1000-pixel photo in a 320-pixel input
    left, right = (0, 0, 600, 1000), (400, 0, 1000, 1000)
    whole = _candidates(
        [
            (100, 100, 120, 120, 0.9, 0),  # small (6 input px), inside the left tile: the tile's
            (100, 600, 300, 800, 0.7, 4),  # large (64 input px): the whole image's box stays
            (350, 500, 650, 700, 0.8, 1),  # across both tiles' inner edges: only here whole
        ]
    )
    tiled = [
        (
            left,
            _candidates(
                [
                    (101, 101, 121, 121, 0.6, 2),
                    (102, 602, 298, 798, 0.99, 5),  # the large one again: left to the whole
                    (350, 500, 600, 700, 0.95, 1),  # cut by the tile's inner edge
                ]
            ),
        ),
        (right, _candidates([(400, 500, 650, 700, 0.9, 1), (700, 10, 720, 30, 0.5, 3)])),
    ]
    out = merged(whole, tiled, size, gain)
    rows = {
        (tuple(np.round(b).astype(int)), float(s), int(c))
        for b, s, c in zip(out.boxes, out.scores, out.class_ids, strict=True)
    }
    assert rows == {
        ((101, 101, 121, 121), 0.6, 2),  # the tile's, not the whole image's 0.9 of class 0
        ((100, 600, 300, 800), 0.7, 4),  # the whole image's, not the tile's 0.99 of class 5
        ((350, 500, 650, 700), 0.8, 1),  # the whole image's: each tile cut it
        ((700, 10, 720, 30), 0.5, 3),  # seen by a tile alone
    }
    assert list(out.scores) == sorted(out.scores, reverse=True)


# -- the real models on a real wide drone view -------------------------------------------------

WIDE = FreeCamera(  # garden from 13 units away through a 73° lens (the scene camera's is 45°)
    position=(8.5702, -0.4399, 9.4468),
    quaternion_wxyz=(0.2323, -0.5817, -0.7631, 0.159),
    fov_deg=72.5781,
)
PHOTO = (1280, 960)


@pytest.fixture(scope="module")
def wide_view(
    engine: RenderEngine, catalog: SceneCatalog
) -> Iterator[tuple[bytes, RenderAnnotations]]:
    request = RenderRequest(
        scene="garden", camera=WIDE, width=PHOTO[0], height=PHOTO[1], spp=16, seed=4
    )
    with LocalRenderer(catalog, engine=engine) as renderer:
        yield renderer.render_png(request), renderer.annotations(request)


def _detect(catalog: SceneCatalog, data: bytes, tiles: int) -> DetectResponse:
    async def run() -> DetectResponse:
        detector = Detector(
            load_scene_model(catalog.get("garden")), DetectorSettings(detector_tiles=tiles)
        )
        await detector.start()
        try:
            return await detector.detect(data)
        finally:
            await detector.close()

    return asyncio.run(run())


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return float(box_iou(np.asarray(a, dtype=np.float64), np.asarray([b], dtype=np.float64))[0])


def _named_right(response: DetectResponse, truth: RenderAnnotations) -> set[str]:
    """The objects at least 60 % visible that a detection covers (IoU ≥ 0.5) under their name."""
    return {
        o.name
        for o in truth.objects
        if o.box is not None and o.visible_fraction >= 0.6
        for d in response.detections
        if d.label == o.name and _iou(d.box, o.box) >= 0.5
    }


def test_tiles_name_the_small_objects_of_a_wide_view_right(catalog, wide_view):
    png, truth = wide_view
    usable = {o.name for o in truth.objects if o.box is not None and o.visible_fraction >= 0.6}
    assert len(usable) == 6
    small = [o.box[2] - o.box[0] for o in truth.objects if o.box is not None]
    assert max(small) < 80  # ~16 of the 320 input's pixels: the whole photo shrinks them 4 times
    whole = _named_right(_detect(catalog, png, 0), truth)
    tiled = _named_right(_detect(catalog, png, 2), truth)
    assert len(tiled) >= len(whole) + 2, (whole, tiled)


def test_a_view_at_the_input_size_is_detected_as_before(catalog, wide_view):
    png, _ = wide_view
    rgb = cv2.cvtColor(
        cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )
    small = encode_png(
        np.asarray(cv2.resize(rgb, (320, 240), interpolation=cv2.INTER_AREA), dtype=np.uint8)
    )
    assert _detect(catalog, small, 2).detections == _detect(catalog, small, 0).detections


def test_a_large_jpeg_decoded_shrunk_is_tiled_in_its_own_pixels(catalog, wide_view):
    """A 2560 x 1920 JPEG is decoded halved by libjpeg and tiled in those pixels: its boxes come
    back in the JPEG's pixels, twice the 1280-pixel PNG's."""
    png, _ = wide_view
    rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    big = cv2.resize(rgb, (2 * PHOTO[0], 2 * PHOTO[1]), interpolation=cv2.INTER_LINEAR)
    ok, jpeg = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 98])
    assert ok
    at_png = _detect(catalog, png, 2)
    at_jpeg = _detect(catalog, jpeg.tobytes(), 2)
    assert at_jpeg.image_size == (2 * PHOTO[0], 2 * PHOTO[1])
    confident = [d for d in at_png.detections if d.confidence >= 0.5]
    assert len(confident) >= 4
    for d in confident:
        twin = max(at_jpeg.detections, key=lambda e: _iou(e.box, tuple(2 * v for v in d.box)))
        assert twin.label == d.label
        np.testing.assert_allclose(twin.box, [2 * v for v in d.box], atol=6.0)
