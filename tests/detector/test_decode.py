"""Safe image decoding: formats, sizes from headers, and every way an upload can be wrong."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.common.errors import ServiceError
from services.common.images import decode_image, encode_ppm, media_type_of, read_header
from tests.support import ROOT

LIMITS = {"max_pixels": 4_000_000, "max_side": 8192}


def encode(ext: str, image: np.ndarray, params: list[int] | None = None) -> bytes:
    ok, buffer = cv2.imencode(ext, image, params or [])
    assert ok
    return buffer.tobytes()


def picture(height: int = 48, width: int = 64) -> np.ndarray:
    """A smooth BGR test picture (compresses like a photo, not like noise)."""
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x * 255 // width, y * 255 // height, (x + y) % 256], axis=-1).astype(np.uint8)


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def bomb_png(width: int, height: int) -> bytes:
    """A tiny PNG declaring ``width x height`` grey pixels (its data inflates to all of them)."""
    row = b"\x00" + b"\x00" * width
    data = zlib.compress(row * min(height, 64), 9)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + png_chunk(b"IHDR", ihdr)
        + png_chunk(b"IDAT", data)
        + png_chunk(b"IEND", b"")
    )


def problem_of(data: bytes, **limits: int) -> ServiceError:
    with pytest.raises(ServiceError) as caught:
        decode_image(data, **{**LIMITS, **limits})
    return caught.value


@pytest.mark.parametrize(
    ("ext", "image"),
    [
        (".png", picture()),
        (".jpg", picture()),
        (".png", picture()[..., 0]),  # grey
        (".png", np.dstack([picture(), np.full((48, 64), 200, np.uint8)])),  # with alpha
        (".png", picture().astype(np.uint16) * 257),  # 16-bit
        (".jpg", picture()[..., 0]),
    ],
)
def test_headers_and_decoding_agree(ext, image):
    data = encode(ext, image)
    header = read_header(data)
    assert (header.width, header.height) == (64, 48)
    assert header.format == ("png" if ext == ".png" else "jpeg")
    rgb = decode_image(data, **LIMITS)
    assert rgb.shape == (48, 64, 3)
    assert rgb.dtype == np.uint8


def test_progressive_jpeg_header():
    data = encode(".jpg", picture(30, 70), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert (read_header(data).width, read_header(data).height) == (70, 30)


def test_decoded_images_are_rgb():
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 2] = 255  # red, in OpenCV's BGR order
    rgb = decode_image(encode(".png", bgr), **LIMITS)
    assert rgb[0, 0].tolist() == [255, 0, 0]


def test_empty_upload():
    problem = problem_of(b"")
    assert (problem.status, problem.slug, problem.field) == (422, "empty-image", "image")


@pytest.mark.parametrize(
    "data",
    [b"hello", b"GIF89a" + b"\x00" * 40, b"\x00" * 100, b"II*\x00" + b"\x00" * 100, b"{}"],
)
def test_not_png_or_jpeg_is_415(data):
    problem = problem_of(data)
    assert (problem.status, problem.slug) == (415, "unsupported-image-format")


@pytest.mark.parametrize("ext", [".png", ".jpg"])
@pytest.mark.parametrize("keep", [0.05, 0.3, 0.6, 0.95, -1])
def test_truncated_images_are_422(ext, keep):
    data = encode(ext, picture(96, 128))
    cut = data[:keep] if keep == -1 else data[: max(3, int(len(data) * keep))]
    problem = problem_of(cut)
    assert (problem.status, problem.slug) == (422, "invalid-image")


def test_corrupt_png_data_is_422():
    data = bytearray(encode(".png", picture(96, 128)))
    data[60:80] = b"\xff" * 20  # inside the IDAT chunk
    assert problem_of(bytes(data)).status == 422


@pytest.mark.parametrize("size", [(60000, 60000), (4096, 4096), (100_000, 1)])
def test_decompression_bombs_are_refused_from_the_header(size):
    data = bomb_png(*size)
    assert len(data) < 300_000
    assert (read_header(data).width, read_header(data).height) == size
    problem = problem_of(data, max_pixels=1_000_000, max_side=8192)
    assert (problem.status, problem.slug) == (413, "image-too-large")


def test_jpeg_size_limit_comes_from_the_frame_header():
    data = encode(".jpg", picture(100, 300))
    assert problem_of(data, max_pixels=10_000).status == 413
    assert problem_of(data, max_side=200).status == 413
    assert decode_image(data, max_pixels=30_000, max_side=300).shape == (100, 300, 3)


def test_zero_sized_png_header_is_422():
    ihdr = struct.pack(">IIBBBBB", 0, 10, 8, 0, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IEND", b"")
    assert problem_of(data).status == 422


def test_jpeg_without_a_frame_header_is_422():
    data = b"\xff\xd8" + b"\xff\xda\x00\x02" + b"\x00" * 10 + b"\xff\xd9"
    assert problem_of(data).status == 422


def ppm(rgb: np.ndarray) -> bytes:
    return encode_ppm(rgb)


def test_ppm_round_trips_exactly():
    rgb = picture()[..., ::-1].copy()
    data = ppm(rgb)
    assert data.startswith(b"P6\n64 48\n255\n")
    assert media_type_of(data) == "image/x-portable-pixmap"
    header = read_header(data)
    assert (header.format, header.width, header.height) == ("ppm", 64, 48)
    decoded = decode_image(data, **LIMITS)
    assert np.array_equal(decoded, rgb)
    decoded[0, 0] = 0  # a writable copy, not a view of the upload
    assert np.array_equal(decode_image(data, **LIMITS), rgb)


def test_ppm_agrees_with_opencv_and_allows_comments():
    rgb = picture(5, 7)[..., ::-1].copy()
    data = b"P6 # made by hand\n7\t5\n# max:\n255\r" + rgb.tobytes()
    assert np.array_equal(decode_image(data, **LIMITS), rgb)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(bgr[..., ::-1], rgb)


@pytest.mark.parametrize(
    ("data", "status"),
    [
        (b"P6", 422),  # no header
        (b"P6 7 5 255", 422),  # no separator before the pixels
        (b"P67 5 255\n", 422),  # no whitespace after the magic
        (b"P6 7 5 255\n" + b"\x00" * 104, 422),  # one byte short
        (b"P6 0 5 255\n", 422),
        (b"P6 7 -5 255\n" + b"\x00" * 105, 422),
        (b"P6 7 5 # comment without end", 422),
        (b"P6 1234567890 5 255\n", 422),  # more digits than any real size
        (b"P6 7 5 65535\n" + b"\x00" * 210, 415),  # 16-bit
        (b"P3 1 1 255\n0 0 0\n", 415),  # plain (ASCII) PPM
        (b"P5 1 1 255\n\x00", 415),  # grey PGM
    ],
)
def test_bad_ppm_is_refused(data, status):
    assert problem_of(data).status == status


def test_ppm_size_limit_comes_from_the_header():
    data = b"P6\n60000 60000\n255\n" + b"\x00" * 30
    problem = problem_of(data, max_pixels=1_000_000)
    assert (problem.status, problem.slug) == (413, "image-too-large")


def outcome(data: bytes) -> tuple[np.ndarray | None, int]:
    """The decoded image and 200, or None and the error's status."""
    try:
        return decode_image(data, **LIMITS), 200
    except ServiceError as exc:
        return None, exc.status


VALID = [encode(".png", picture()), encode(".jpg", picture()), encode_ppm(picture())]


@given(
    base=st.sampled_from(VALID),
    cut=st.integers(0, 20_000),
    flips=st.lists(st.tuples(st.integers(0, 20_000), st.integers(0, 255)), max_size=6),
)
@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)
def test_mangled_images_decode_or_fail_cleanly(base, cut, flips):
    """Truncated or bit-flipped PNG/JPEG/PPM data is either decoded to its declared size or refused
    with a 4xx service error - never any other exception."""
    data = bytearray(base[: max(1, cut % (len(base) + 1))])
    for position, value in flips:
        if data:
            data[position % len(data)] = value
    rgb, status = outcome(bytes(data))
    if rgb is None:
        assert 400 <= status < 500
    else:
        header = read_header(bytes(data))
        assert rgb.shape == (header.height, header.width, 3)


@given(data=st.binary(max_size=512))
@settings(max_examples=200, deadline=None, database=None)
def test_arbitrary_bytes_fail_cleanly(data):
    rgb, status = outcome(data)
    assert rgb is not None or 400 <= status < 500


def test_importing_the_detector_caps_opencv_before_it_loads(tmp_path):
    """In a fresh interpreter the package sets OPENCV_IO_MAX_IMAGE_PIXELS before cv2 is loaded,
    so even a direct cv2.imdecode refuses an image over the hard cap before allocating it
    (without the cap, OpenCV would try, and fail only on the missing rows)."""
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(bomb_png(9000, 9000))  # 81 M pixels > 2**26
    script = (
        "import os, sys\n"
        "import services.common.images\n"
        "import cv2, numpy as np\n"
        "assert os.environ['OPENCV_IO_MAX_IMAGE_PIXELS'] == str(1 << 26)\n"
        "data = np.fromfile(sys.argv[1], np.uint8)\n"
        "try:\n"
        "    cv2.imdecode(data, cv2.IMREAD_COLOR)\n"
        "except cv2.error as exc:\n"
        "    print('capped' if 'CV_IO_MAX_IMAGE_PIXELS' in str(exc) else exc)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_IO_MAX_IMAGE_PIXELS"}
    result = subprocess.run(
        [sys.executable, "-c", script, str(bomb)],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "capped"  # refused from the header, not a failed decode


# -- truncated JPEG scans ----------------------------------------------------------------------


def photo(height: int = 96, width: int = 128) -> np.ndarray:
    """A BGR picture with texture everywhere, so every block has data of its own."""
    rng = np.random.default_rng(5)
    return cv2.GaussianBlur(rng.integers(0, 256, (height, width, 3), dtype=np.uint8), (5, 5), 0)


JPEG_KINDS = {
    "baseline-420": [],
    "baseline-444": [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444],
    "progressive": [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],
}


def cuts(data: bytes) -> list[int]:
    """Where to cut a JPEG: a fifth, half and nine tenths into its data, and for a progressive
    one, also half-way into each scan but the last."""
    points = [int(len(data) * keep) for keep in (0.2, 0.5, 0.9)]
    scans = [i for i in range(len(data) - 1) if data[i : i + 2] == b"\xff\xda"]
    points += [(a + b) // 2 for a, b in zip(scans, scans[1:], strict=False)]
    return sorted(p for p in points if p < scans[-1] or len(scans) == 1)


@pytest.mark.parametrize("kind", JPEG_KINDS)
def test_a_truncated_jpeg_with_an_end_marker_appended_is_422(kind):
    """OpenCV decodes such a file without complaint, the missing blocks grey or the missing
    scans not applied; it is refused."""
    data = encode(".jpg", photo(), JPEG_KINDS[kind])
    for cut in cuts(data):
        mangled = data[:cut] + b"\xff\xd9"
        assert cv2.imdecode(np.frombuffer(mangled, np.uint8), cv2.IMREAD_COLOR) is not None
        problem = problem_of(mangled)
        assert (problem.status, problem.slug, problem.field) == (422, "invalid-image", "image")
        assert "truncated" in problem.detail, problem.detail


@pytest.mark.parametrize("kind", JPEG_KINDS)
@pytest.mark.parametrize("shade", [0, 128, 255])
def test_complete_jpegs_decode_however_they_end(kind, shade):
    """Whole files decode, also one that really ends in libjpeg's fill grey."""
    bgr = photo()
    bgr[-40:, -40:] = shade
    for image in (bgr, np.full((96, 128, 3), shade, np.uint8)):
        rgb = decode_image(encode(".jpg", image, JPEG_KINDS[kind]), **LIMITS)
        assert rgb.shape == (96, 128, 3)


@pytest.mark.parametrize(
    ("ext", "image", "channels", "depth"),
    [
        (".png", picture(), 3, 8),
        (".png", picture()[..., 0], 1, 8),
        (".png", np.dstack([picture(), picture()[..., :1]]), 4, 8),
        (".png", picture().astype(np.uint16) * 257, 3, 16),
        (".png", np.dstack([picture(), picture()[..., :1]]).astype(np.uint16), 4, 16),
        (".jpg", picture(), 3, 8),
        (".jpg", picture()[..., 0], 1, 8),
    ],
)
def test_headers_give_the_bytes_a_decode_holds(ext, image, channels, depth):
    header = read_header(encode(ext, image))
    assert (header.channels, header.bit_depth) == (channels, depth)
    assert header.decoded_bytes == 48 * 64 * max(3, channels * depth // 8)
    assert read_header(encode_ppm(picture())).decoded_bytes == 48 * 64 * 3


def test_a_png_of_an_impossible_depth_is_422():
    ihdr = struct.pack(">IIBBBBB", 10, 10, 16, 3, 0, 0, 0)  # a 16-bit palette
    data = b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IEND", b"")
    assert problem_of(data).status == 422


@pytest.mark.parametrize(("at_least", "factor"), [((64, 48), 8), ((129, 96), 4), ((300, 200), 2)])
def test_a_large_jpeg_decodes_already_shrunk_towards_the_size_asked(at_least, factor):
    """``at_least``: a JPEG decoded by libjpeg's scaled IDCT, the most of 2, 4 and 8 that keeps
    it that large, its grey close to the whole decode's shrunk by area (the same pixel grid); a
    PNG, or a JPEG whose sides the factor does not divide, whole."""
    bgr = cv2.resize(photo(), (1024, 768), interpolation=cv2.INTER_CUBIC)
    data = encode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    whole = cv2.cvtColor(decode_image(data, **LIMITS), cv2.COLOR_RGB2GRAY)
    small = cv2.cvtColor(decode_image(data, **LIMITS, at_least=at_least), cv2.COLOR_RGB2GRAY)
    assert small.shape == (768 // factor, 1024 // factor)
    area = cv2.resize(whole, small.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(small.astype(int) - area.astype(int)).mean() < 2.0
    assert decode_image(encode(".png", bgr), **LIMITS, at_least=at_least).shape == (768, 1024, 3)
    odd = encode(".jpg", cv2.resize(bgr, (1001, 751)))
    assert decode_image(odd, **LIMITS, at_least=at_least).shape == (751, 1001, 3)


@pytest.mark.parametrize("kind", JPEG_KINDS)
def test_a_truncated_jpeg_decoded_shrunk_is_still_422(kind):
    data = encode(".jpg", cv2.resize(photo(), (1024, 768)), JPEG_KINDS[kind])
    for cut in cuts(data):
        with pytest.raises(ServiceError) as caught:
            decode_image(data[:cut] + b"\xff\xd9", **LIMITS, at_least=(128, 96))
        assert caught.value.status == 422
        assert "truncated" in caught.value.detail, caught.value.detail
