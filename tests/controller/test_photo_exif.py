"""The photo's focal length from its EXIF (:mod:`services.controller.photo_exif`): the tags a
camera writes, read into pixels; crops, absurd values and broken metadata not used; and a free
search submitted without intrinsics records them (``source="exif"``) unless told not to."""

from __future__ import annotations

import io
import math

import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from services.controller.photo_exif import exif_focal, exif_intrinsics
from services.controller.photo_metadata import read_metadata
from tests.support import submitted_search

T = ExifTags.Base


def jpeg(size: tuple[int, int], tags: dict[int, object] | None = None) -> bytes:
    """A grey JPEG of ``size`` whose EXIF sub-IFD holds ``tags``."""
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif).update(tags or {})
    out = io.BytesIO()
    Image.new("RGB", size, (90, 90, 90)).save(out, "JPEG", exif=exif)
    return out.getvalue()


def horizontal_fov_deg(focal_px: float, width: int) -> float:
    return math.degrees(2.0 * math.atan(width / (2.0 * focal_px)))


def test_the_35mm_equivalent_gives_the_focal_length_over_the_diagonal():
    found = exif_focal(read_metadata(jpeg((640, 480), {T.FocalLengthIn35mmFilm: 24})), (640, 480))
    assert found is not None
    # 24 mm on the 43.27 mm full-frame diagonal: the diagonal's 800 px span 2·atan(43.27/48)
    assert found.focal_px == pytest.approx(24.0 * 800.0 / math.hypot(36.0, 24.0))
    assert "FocalLengthIn35mmFilm 24" in found.tag


def test_a_resized_photo_keeps_its_field_of_view():
    tags = {T.FocalLengthIn35mmFilm: 28, T.ExifImageWidth: 4000, T.ExifImageHeight: 3000}
    small = exif_focal(read_metadata(jpeg((400, 300), tags)), (400, 300))
    large = exif_focal(read_metadata(jpeg((1600, 1200), tags)), (1600, 1200))
    assert small is not None
    assert large is not None
    assert horizontal_fov_deg(small.focal_px, 400) == pytest.approx(
        horizontal_fov_deg(large.focal_px, 1600)
    )


def test_the_focal_plane_resolution_gives_pixels_on_the_sensor_scaled_to_the_image():
    # a 6.3 mm wide sensor of 4000 px (pixels per inch), a 4.5 mm lens: f = 4.5·4000/6.3 px
    tags = {
        T.FocalLength: IFDRational(45, 10),
        T.FocalPlaneXResolution: IFDRational(4000 * 254, 63),
        T.FocalPlaneResolutionUnit: 2,
        T.ExifImageWidth: 4000,
        T.ExifImageHeight: 3000,
    }
    found = exif_focal(read_metadata(jpeg((800, 600), tags)), (800, 600))
    assert found is not None
    assert found.focal_px == pytest.approx(4.5 * 4000 / 6.3 * 800 / 4000)
    # in millimetres per unit too (Exif 3's unit 4)
    tags[T.FocalPlaneXResolution] = IFDRational(4000 * 10, 63)
    tags[T.FocalPlaneResolutionUnit] = 4
    again = exif_focal(read_metadata(jpeg((800, 600), tags)), (800, 600))
    assert again is not None
    assert again.focal_px == pytest.approx(found.focal_px)


@pytest.mark.parametrize(
    ("tags", "size"),
    [
        ({}, (640, 480)),  # no focal length stated
        # a crop: the camera's 4:3 frame stored as 16:9
        (
            {T.FocalLengthIn35mmFilm: 24, T.ExifImageWidth: 4000, T.ExifImageHeight: 3000},
            (640, 360),
        ),
        ({T.FocalLengthIn35mmFilm: 0}, (640, 480)),  # "unknown", as cameras write it
        ({T.FocalLengthIn35mmFilm: 1}, (640, 480)),  # a field of view of 170° or more
        ({T.FocalLength: IFDRational(45, 10)}, (640, 480)),  # no sensor size: no pixels
        (
            {T.FocalLength: IFDRational(1, 0), T.FocalPlaneXResolution: 1000},
            (640, 480),
        ),  # a rational over zero
        (
            {
                T.FocalLength: IFDRational(45, 10),
                T.FocalPlaneXResolution: 1000,
                T.FocalPlaneResolutionUnit: 9,
            },
            (640, 480),
        ),  # a unit no standard names
    ],
)
def test_what_cannot_be_trusted_gives_no_focal_length(tags, size):
    assert exif_focal(read_metadata(jpeg(size, tags)), size) is None


def test_broken_or_absent_metadata_is_no_focal_length_not_an_error():
    good = jpeg((640, 480), {T.FocalLengthIn35mmFilm: 24})
    start = good.index(b"Exif\x00\x00")
    broken = good[: start + 6] + b"\xde\xad" * 8 + good[start + 22 :]
    assert exif_focal(read_metadata(broken), (640, 480)) is None
    assert exif_focal(read_metadata(good[:40]), (640, 480)) is None
    png = io.BytesIO()
    Image.new("RGB", (64, 48)).save(png, "PNG")
    assert exif_focal(read_metadata(png.getvalue()), (64, 48)) is None
    assert exif_focal(read_metadata(b"not an image"), (64, 48)) is None


def test_the_intrinsics_say_they_come_from_the_exif():
    k = exif_intrinsics(read_metadata(jpeg((640, 480), {T.FocalLengthIn35mmFilm: 24})), (640, 480))
    assert k is not None
    assert k.source == "exif"
    assert k.fx_px == k.fy_px == pytest.approx(24.0 * 800.0 / math.hypot(36.0, 24.0))
    assert k.cx_px is None  # the image's centre
    assert exif_intrinsics(read_metadata(jpeg((640, 480))), (640, 480)) is None


@pytest.mark.anyio
@pytest.mark.parametrize(
    ("params", "recorded"),
    [
        ({"mode": "free"}, {"source": "exif"}),
        ({"mode": "free", "exif": "false"}, None),
        ({"mode": "free", "fov_deg": "50"}, {"source": "given", "fov_deg": 50.0}),
        ({}, None),  # a hemisphere search has no intrinsics
    ],
)
async def test_a_free_search_records_the_exif_focal_length_unless_given_or_told_not_to(
    controller, params, recorded
):
    _, client = controller
    image = jpeg((320, 240), {T.FocalLengthIn35mmFilm: 35})
    intrinsics = (await submitted_search(client, image, params))["intrinsics"]
    if recorded is None:
        assert intrinsics is None
        return
    assert intrinsics is not None
    assert intrinsics.items() >= recorded.items()
    if recorded["source"] == "exif":
        assert intrinsics["fx_px"] == pytest.approx(35.0 * 400.0 / math.hypot(36.0, 24.0))
