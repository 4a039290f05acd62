"""The detector's HTTP API in process (ASGI transport, lifespan run) with synthetic ONNX models:
pixel-exact boxes through the whole pipeline, batching, and a problem+json 4xx for every kind of
bad upload."""

from __future__ import annotations

import asyncio
import struct
import zlib
from collections.abc import AsyncIterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from asgi_lifespan import LifespanManager

from services.common.images import encode_ppm, media_type_of
from services.detector.app import create_app
from services.detector.letterbox import PAD_VALUE, fit
from services.detector.model import ModelError
from services.detector.settings import DetectorSettings
from services.detector.synthetic import channel_mean_model, constant_model
from tests.support import in_process

pytestmark = pytest.mark.anyio

CLASSES = ["sphere", "cube"]
# Anchors in input pixels of a 320x320 network: (cx, cy, w, h, [sphere, cube]).
ANCHORS = [
    (100, 120, 40, 80, [0.9, 0.0]),  # A: input box (80, 80)-(120, 160)
    (101, 121, 40, 80, [0.8, 0.0]),  # A again, a little shifted: suppressed by NMS
    (100, 120, 40, 80, [0.0, 0.7]),  # A's place, the other class: kept
    (200, 200, 40, 40, [0.1, 0.0]),  # under the default threshold
    (250, 20, 20, 20, [0.95, 0.0]),  # in the padding of both test images: dropped
]
UPLOAD_LIMIT = 200_000


def predictions() -> np.ndarray:
    return np.array([[*row[:4], *row[4]] for row in ANCHORS], dtype=np.float32).T


def png(rgb: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return buffer.tobytes()


def jpeg(rgb: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return buffer.tobytes()


def grey(width: int, height: int) -> np.ndarray:
    return np.full((height, width, 3), 128, np.uint8)


def bomb_png(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * (width + 1) * 16, 9)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("detector-models")
    constant_model(directory / "constant.onnx", predictions(), classes=CLASSES)
    channel_mean_model(directory / "means.onnx", [160, 160, 64, 64])
    channel_mean_model(directory / "means-b1.onnx", [160, 160, 64, 64], batch=1)
    return directory


def settings_for(model: Path, **overrides) -> DetectorSettings:
    values = {
        "detector_model": model,
        "detector_threads": 1,
        "detector_max_upload_bytes": UPLOAD_LIMIT,
        "detector_max_image_pixels": 1_000_000,
        **overrides,
    }
    return DetectorSettings(**values)


async def serve(settings: DetectorSettings) -> AsyncIterator[httpx.AsyncClient]:
    async with in_process(create_app(settings), "http://detector", settings.token()) as client:
        yield client


@pytest.fixture(scope="module")
async def client(model_dir) -> AsyncIterator[httpx.AsyncClient]:
    async for c in serve(settings_for(model_dir / "constant.onnx")):
        yield c


async def detect(
    client: httpx.AsyncClient, data: bytes, *, raw: bool = False, **params
) -> httpx.Response:
    """``POST /detect`` of ``data`` as a form's file, or (``raw``) as the body itself."""
    if raw:
        media_type = media_type_of(data)
        headers = {"content-type": "image/png" if "octet" in media_type else media_type}
        return await client.post("/detect", content=data, headers=headers, params=params)
    return await client.post("/detect", files={"image": ("x", data, "image/png")}, params=params)


HOW = pytest.mark.parametrize("raw", [False, True], ids=["multipart", "raw"])


# -- answers -----------------------------------------------------------------------------------


async def test_health(client):
    body = (await client.get("/health")).json()
    assert body["status"] == "ok"
    assert body["service"] == "detector"
    assert body["model"] == "constant"
    assert body["in_flight"] == 0
    assert body["providers"] == ["CPUExecutionProvider"]
    assert body["intra_op_threads"] == 1
    assert body["max_batch"] == 8


async def test_model_info(client, model_dir):
    body = (await client.get("/model")).json()
    assert body["classes"] == CLASSES
    assert body["input_size"] == [320, 320]
    assert len(body["sha256"]) == 64


@pytest.mark.parametrize(
    ("size", "encode", "expected"),
    [
        # scale 0.5, 70 rows of padding on top
        (
            (640, 360),
            png,
            [("sphere", [160, 20, 240, 180], 0.9), ("cube", [160, 20, 240, 180], 0.7)],
        ),
        # scale 0.8, 80 columns of padding on the left
        ((200, 400), jpeg, [("sphere", [0, 100, 50, 200], 0.9), ("cube", [0, 100, 50, 200], 0.7)]),
        # no padding: the last anchor lies in the image
        (
            (320, 320),
            png,
            [
                ("sphere", [240, 10, 260, 30], 0.95),
                ("sphere", [80, 80, 120, 160], 0.9),
                ("cube", [80, 80, 120, 160], 0.7),
            ],
        ),
    ],
)
@HOW
async def test_boxes_come_back_in_pixels_of_the_upload(client, size, encode, expected, raw):
    response = await detect(client, encode(grey(*size)), raw=raw)
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["image_size"] == list(size)
    assert body["model"]["name"] == "constant"
    assert body["inference_ms"] >= 0
    found = [(d["label"], d["class_id"], d["box"]) for d in body["detections"]]
    assert found == [(label, CLASSES.index(label), box) for label, box, _ in expected]
    confidences = [d["confidence"] for d in body["detections"]]
    assert confidences == pytest.approx([conf for *_, conf in expected])


async def test_query_overrides(client):
    image = png(grey(640, 360))
    low = (await detect(client, image, conf=0.05)).json()["detections"]
    assert [d["box"] for d in low][-1] == [360.0, 220.0, 440.0, 300.0]
    assert len(low) == 3
    assert (await detect(client, image, conf=1.0)).json()["detections"] == []
    one = (await detect(client, image, max_detections=1)).json()["detections"]
    assert [d["label"] for d in one] == ["sphere"]


async def test_detections_carry_the_objects_colour(client):
    image = grey(640, 360)
    cv2.ellipse(image, (200, 100), (38, 78), 0, 0, 360, (30, 90, 220), thickness=-1)
    body = (await detect(client, png(image))).json()
    colours = [d["color"] for d in body["detections"]]
    assert len(colours) == 2
    for colour in colours:
        assert colour == pytest.approx([30, 90, 220], abs=1)


async def test_a_large_jpeg_is_detected_from_a_shrunk_decode_like_the_whole_image(model_dir):
    """A JPEG at least twice the network input is decoded shrunk (here 1280 x 1280 by 2, into
    320 x 320): its boxes come back in its own pixels as those of the whole image (a PNG of the
    same pixels), and the colour is measured where they are."""
    image = grey(1280, 1280)
    cv2.ellipse(image, (400, 480), (76, 156), 0, 0, 360, (30, 90, 220), thickness=-1)
    settings = settings_for(
        model_dir / "constant.onnx",
        detector_max_image_pixels=4_000_000,
        detector_max_upload_bytes=10_000_000,
    )
    async for client in serve(settings):
        whole = (await detect(client, png(image))).json()
        shrunk = (await detect(client, jpeg(image))).json()
    assert shrunk["image_size"] == whole["image_size"] == [1280, 1280]
    assert [d["box"] for d in shrunk["detections"]] == [d["box"] for d in whole["detections"]]
    on_it = [d for d in shrunk["detections"] if d["box"] == [320.0, 320.0, 480.0, 640.0]]
    assert len(on_it) == 2  # anchor A, both classes, four times its input box
    for a, b in zip(shrunk["detections"], whole["detections"], strict=True):
        if a in on_it:
            assert a["color"] == pytest.approx(b["color"], abs=3)
            assert a["color"] == pytest.approx([30, 90, 220], abs=4)
        else:
            assert a["color"] is b["color"] is None  # bare ground


async def test_ppm_uploads_are_detected_like_png(client):
    image = grey(320, 180)  # under the test upload limit uncompressed
    cv2.ellipse(image, (100, 50), (19, 39), 0, 0, 360, (30, 90, 220), thickness=-1)
    ppm = encode_ppm(image)
    from_png = await detect(client, png(image))
    from_ppm = await client.post("/detect", files={"image": ("x", ppm, "image/x-portable-pixmap")})
    assert from_ppm.status_code == 200, from_ppm.text
    assert from_ppm.json()["detections"] == from_png.json()["detections"]
    raw_ppm = await detect(client, ppm, raw=True)  # what the controller sends
    assert raw_ppm.status_code == 200, raw_ppm.text
    assert raw_ppm.json()["detections"] == from_png.json()["detections"]


async def test_colour_is_null_on_bare_ground(client):
    body = (await detect(client, png(grey(640, 360)))).json()
    assert [d["color"] for d in body["detections"]] == [None, None]


async def test_the_network_sees_rgb_scaled_to_one_with_grey_padding(model_dir):
    """The channel-mean model reports the mean of each input channel: a pure red 640x360 image
    fills 320x180 of the 320x320 input, the rest is grey 114."""
    async for client in serve(settings_for(model_dir / "means.onnx")):
        image = np.zeros((360, 640, 3), np.uint8)
        image[..., 0] = 255
        body = (await detect(client, png(image), conf=0.0)).json()
        scores = {d["label"]: d["confidence"] for d in body["detections"]}
        image_share = 180 / 320
        grey_share = (1 - image_share) * PAD_VALUE / 255
        assert scores["red"] == pytest.approx(image_share + grey_share, abs=1e-4)
        assert scores["green"] == pytest.approx(grey_share, abs=1e-4)
        assert scores["blue"] == pytest.approx(grey_share, abs=1e-4)


async def test_concurrent_requests_are_batched_and_answered_in_order(model_dir):
    """Six images of different colours sent at once share runs; each answer has its own
    image's channel means."""
    settings = settings_for(model_dir / "means.onnx", detector_batch_window_ms=50.0)
    async for client in serve(settings):
        colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 255, 255), (9, 9, 9)]
        images = []
        for colour in colours:
            image = np.zeros((320, 320, 3), np.uint8)
            image[:] = colour
            images.append(png(image))
        responses = await asyncio.gather(*(detect(client, i, conf=0.0) for i in images))
        for colour, response in zip(colours, responses, strict=True):
            scores = {d["label"]: d["confidence"] for d in response.json()["detections"]}
            got = [scores.get(name, 0.0) for name in ("red", "green", "blue")]
            assert got == pytest.approx([c / 255 for c in colour], abs=1e-4)
        health = (await client.get("/health")).json()
        assert health["images_run"] == 6
        assert health["batches_run"] < 6


async def test_fixed_batch_models_run_one_at_a_time(model_dir):
    async for client in serve(settings_for(model_dir / "means-b1.onnx")):
        responses = await asyncio.gather(*(detect(client, png(grey(64, 64))) for _ in range(3)))
        assert all(r.status_code == 200 for r in responses)
        health = (await client.get("/health")).json()
        assert (health["max_batch"], health["batches_run"]) == (1, 3)


async def test_too_many_requests_in_flight_is_503(model_dir):
    settings = settings_for(
        model_dir / "constant.onnx", detector_max_in_flight=1, detector_batch_window_ms=100.0
    )
    async for client in serve(settings):
        first = asyncio.create_task(detect(client, png(grey(64, 64))))
        await asyncio.sleep(0.02)  # the first now waits out its 100 ms batching window
        second = await detect(client, png(grey(64, 64)))
        assert second.status_code == 503
        assert second.headers["retry-after"] == "1"
        assert second.json()["type"] == "urn:cosmos:problem:detector-busy"
        assert (await first).status_code == 200
        assert (await client.get("/health")).json()["in_flight"] == 0


def rgba16_png(side: int) -> bytes:
    """A ``side`` x ``side`` 16-bit RGBA PNG: a few KB that decode to ``side**2 * 3`` bytes and
    state ``side**2 * 8`` bytes of samples."""
    image = np.zeros((side, side, 4), np.uint16)
    image[::7, ::5] = 40_000
    ok, buffer = cv2.imencode(".png", image)
    assert ok
    return buffer.tobytes()


async def test_concurrent_uploads_hold_no_more_decoded_bytes_than_the_budget(model_dir):
    """Twelve 16-bit RGBA images at once, each holding 2 MiB while decoded, against a 5 MB
    budget: all are answered, never more than two held at once."""
    data = rgba16_png(512)
    held = 512 * 512 * 8
    settings = settings_for(
        model_dir / "constant.onnx", detector_max_decode_bytes=5_000_000, detector_max_batch=1
    )
    async for client in serve(settings):
        responses = await asyncio.gather(*(detect(client, data, raw=True) for _ in range(12)))
        assert [r.status_code for r in responses] == [200] * 12
        health = (await client.get("/health")).json()
        assert health["max_decode_bytes"] == 5_000_000
        assert health["decode_bytes_peak"] == 2 * held
        assert health["decode_bytes"] == 0


async def test_uploads_that_wait_too_long_for_decode_bytes_get_503(model_dir):
    settings = settings_for(
        model_dir / "constant.onnx",
        detector_max_decode_bytes=3_000_000,
        detector_decode_wait_s=0.0,
        detector_batch_window_ms=100.0,
    )
    async for client in serve(settings):
        first = asyncio.create_task(detect(client, rgba16_png(512), raw=True))
        await asyncio.sleep(0.05)  # the first holds its bytes through its batching window
        second = await detect(client, rgba16_png(512), raw=True)
        assert second.status_code == 503
        assert second.headers["retry-after"] == "1"
        assert "COSMOS_DETECTOR_MAX_DECODE_BYTES" in second.json()["detail"]
        assert (await first).status_code == 200


async def test_an_image_that_alone_exceeds_the_decode_budget_is_413(model_dir):
    settings = settings_for(model_dir / "constant.onnx", detector_max_decode_bytes=3_000_000)
    async for client in serve(settings):
        response = await detect(client, rgba16_png(700), raw=True)  # 3.9 MB of samples
        assert response.status_code == 413
        problem = response.json()
        assert problem["type"] == "urn:cosmos:problem:image-too-large"
        assert problem["field"] == "image"
        assert "3000000 bytes" in problem["detail"]


def test_a_decode_budget_too_small_for_one_image_is_refused_at_start_up(model_dir):
    with pytest.raises(ValueError, match="COSMOS_DETECTOR_MAX_DECODE_BYTES"):
        settings_for(model_dir / "constant.onnx", detector_max_decode_bytes=2_000_000)


# -- start-up ----------------------------------------------------------------------------------


async def test_a_missing_model_stops_the_start_up_naming_the_file(tmp_path):
    missing = tmp_path / "nowhere" / "detector.onnx"
    app = create_app(settings_for(missing))
    with pytest.raises(ModelError, match=str(missing)):
        async with LifespanManager(app):
            pass


async def test_a_model_of_the_wrong_layout_stops_the_start_up(tmp_path):
    path = constant_model(tmp_path / "three.onnx", predictions(), classes=["a", "b", "c"])
    app = create_app(settings_for(path))
    with pytest.raises(ModelError, match=r"three\.onnx.*channels"):
        async with LifespanManager(app):
            pass


# -- bad requests ------------------------------------------------------------------------------


def truncated_png() -> bytes:
    data = png(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8))
    return data[: len(data) // 2]


BAD_UPLOADS = [
    ("not an image", b"hello, detector", 415, "urn:cosmos:problem:unsupported-image-format"),
    ("a GIF", b"GIF89a" + b"\x00" * 64, 415, "urn:cosmos:problem:unsupported-image-format"),
    ("truncated PNG", truncated_png(), 422, "urn:cosmos:problem:invalid-image"),
    ("zero-size upload", b"", 422, "urn:cosmos:problem:empty-image"),
    ("decompression bomb", bomb_png(50_000, 50_000), 413, "urn:cosmos:problem:image-too-large"),
    ("too many pixels", png(grey(1200, 900)), 413, "urn:cosmos:problem:image-too-large"),
]


@pytest.mark.parametrize(
    ("data", "status", "kind"), [case[1:] for case in BAD_UPLOADS], ids=[c[0] for c in BAD_UPLOADS]
)
@HOW
async def test_bad_uploads_are_4xx_problems(client, data, status, kind, raw):
    response = await detect(client, data, raw=raw)
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert (problem["status"], problem["type"], problem["field"]) == (status, kind, "image")


async def problem(response: httpx.Response, status: int) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    body: dict = response.json()
    assert body["status"] == status
    return body


async def test_missing_image_field(client):
    response = await client.post("/detect", files={"picture": ("x.png", png(grey(8, 8)))})
    assert (await problem(response, 422))["field"] == "image"


async def test_image_sent_as_a_text_field(client):
    response = await client.post(
        "/detect", data={"image": "not a file"}, files={"other": ("x", b"1")}
    )
    assert (await problem(response, 422))["field"] == "image"


@pytest.mark.parametrize(
    ("content", "content_type"),
    [
        (b'{"image": "aGVsbG8="}', "application/json"),
        (png(grey(8, 8)), "image/gif"),
        (png(grey(8, 8)), "text/plain"),
        (png(grey(8, 8)), "application/octet-stream"),
        (b"image=abc", "application/x-www-form-urlencoded"),
        (png(grey(8, 8)), None),
    ],
)
async def test_wrong_content_types_are_415(client, content, content_type):
    headers = {"content-type": content_type} if content_type else {}
    response = await client.post("/detect", content=content, headers=headers)
    body = await problem(response, 415)
    assert body["field"] == "content-type"


@pytest.mark.parametrize(
    ("content", "content_type"),
    [
        (b"garbage without any parts", "multipart/form-data; boundary=xyz"),
        (b"--xyz\r\nContent-Disposition: form-data\r\n\r\n", "multipart/form-data; boundary=xyz"),
        (b"--xyz--\r\n", "multipart/form-data"),  # no boundary parameter
    ],
)
async def test_malformed_multipart_is_4xx(client, content, content_type):
    response = await client.post("/detect", content=content, headers={"content-type": content_type})
    assert 400 <= response.status_code < 500
    assert response.headers["content-type"] == "application/problem+json"


async def test_a_malformed_form_is_400_naming_the_body(client):
    response = await client.post(
        "/detect", content=b"--xyz--\r\n", headers={"content-type": "multipart/form-data"}
    )
    body = await problem(response, 400)
    assert body["field"] == "body"
    assert "multipart" in body["detail"]


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"conf": 2}, "conf"),
        ({"conf": -0.1}, "conf"),
        ({"conf": "nan"}, "conf"),
        ({"conf": "high"}, "conf"),
        ({"max_detections": 0}, "max_detections"),
        ({"max_detections": 5000}, "max_detections"),
    ],
)
async def test_bad_query_parameters_are_422(client, params, field):
    response = await detect(client, png(grey(8, 8)), **params)
    assert (await problem(response, 422))["field"] == field


def multipart(data: bytes, boundary: str = "cosmos-boundary") -> tuple[bytes, str]:
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="image"; filename="x.png"\r\n'
        "Content-Type: image/png\r\n\r\n"
    ).encode()
    return head + data + f"\r\n--{boundary}--\r\n".encode(), boundary


@HOW
async def test_oversized_upload_is_413_by_content_length(client, raw):
    big = png(np.random.default_rng(1).integers(0, 255, (300, 300, 3), dtype=np.uint8))
    assert len(big) > UPLOAD_LIMIT
    response = await detect(client, big, raw=raw)
    assert (await problem(response, 413))["type"] == "urn:cosmos:problem:payload-too-large"


async def test_oversized_chunked_multipart_upload_is_413(client):
    body, boundary = multipart(b"\x89PNG\r\n\x1a\n" + b"\x00" * (UPLOAD_LIMIT + 10))
    chunk = 16_384

    async def stream() -> AsyncIterator[bytes]:
        for start in range(0, len(body), chunk):
            yield body[start : start + chunk]

    response = await client.post(
        "/detect",
        content=stream(),
        headers={"content-type": f"multipart/form-data; boundary={boundary}"},
    )
    assert (await problem(response, 413))["type"] == "urn:cosmos:problem:payload-too-large"


async def test_oversized_chunked_raw_upload_is_413(client):
    body = b"\x89PNG\r\n\x1a\n" + b"\x00" * (UPLOAD_LIMIT + 10)

    async def stream() -> AsyncIterator[bytes]:
        for start in range(0, len(body), 16_384):
            yield body[start : start + 16_384]

    response = await client.post("/detect", content=stream(), headers={"content-type": "image/png"})
    assert (await problem(response, 413))["type"] == "urn:cosmos:problem:payload-too-large"


async def test_chunked_multipart_under_the_limit_is_served(client):
    body, boundary = multipart(png(grey(640, 360)))

    async def stream() -> AsyncIterator[bytes]:
        for start in range(0, len(body), 1000):
            yield body[start : start + 1000]

    response = await client.post(
        "/detect",
        content=stream(),
        headers={"content-type": f"multipart/form-data; boundary={boundary}"},
    )
    assert response.status_code == 200, response.text
    assert len(response.json()["detections"]) == 2


async def test_unknown_route_is_a_problem(client):
    response = await client.get("/detector")
    await problem(response, 404)


@pytest.mark.parametrize(
    ("size", "scale", "pad", "expected"),
    [
        # r = min(320/640, 320/360) = 0.5, 360 rows -> 180, (320 - 180) // 2 = 70 rows on top:
        # x = x_in / 0.5, y = (y_in - 70) / 0.5
        ((640, 360), (0.5, 0.5), (0, 70), [160, 20, 240, 180]),
        # r = min(320/200, 320/400) = 0.8, 200 columns -> 160, (320 - 160) // 2 = 80 on the left:
        # x = (x_in - 80) / 0.8, y = y_in / 0.8
        ((200, 400), (0.8, 0.8), (80, 0), [0, 100, 50, 200]),
    ],
)
def test_the_golden_boxes_are_the_letterbox_inverse_of_anchor_a(size, scale, pad, expected):
    """The expected boxes of ``test_boxes_come_back_in_pixels_of_the_upload``, from the detector's
    own letterbox: anchor A's input box (80, 80)-(120, 160) mapped back into the upload."""
    cx, cy, w, h = ANCHORS[0][:4]
    input_box = np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
    box = fit(size, (320, 320))
    assert box.scale == pytest.approx(scale)
    assert box.pad == pad
    assert box.to_image(input_box).tolist() == expected
