"""A drone's calibrated intrinsics from its photo's XMP (:mod:`services.controller.photo_xmp`):
DJI's DewarpData read into the photo's pixels, scaled with a resize, without distortion when the
photo was dewarped; crops, lenses that fold the photo and broken metadata not used; and a free
search prefers it to the EXIF focal length (``source="calibration"``)."""

from __future__ import annotations

import io
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import ExifTags, Image

from cosmos.bench.variants import dji_xmp
from services.common.contracts.free import CameraAttitude
from services.common.geometry.free_camera import LensDistortion
from services.controller.photo_exif import exif_intrinsics
from services.controller.photo_metadata import read_metadata
from services.controller.photo_xmp import xmp_attitude, xmp_intrinsics
from tests.support import submitted_search

T = ExifTags.Base
P4RTK = LensDistortion(k1=-0.269478, k2=0.115681, p1=-8.75619e-5, p2=-3.06177e-4, k3=-0.0357628)
"""A Phantom 4 RTK's published DewarpData lens (4864 × 3648 photos)."""
SIZE = (4864, 3648)
FOCAL = (3659.78, 3653.17)
CENTRE = (2432.0 - 7.71, 1824.0 + 45.9)


def jpeg(size: tuple[int, int], xmp: bytes | None, tags: dict[int, object] | None = None) -> bytes:
    """A grey JPEG of ``size`` with the ``xmp`` packet and EXIF sub-IFD ``tags``."""
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif).update(tags or {})
    out = io.BytesIO()
    extra = {} if xmp is None else {"xmp": xmp}
    Image.new("RGB", size, (90, 90, 90)).save(out, "JPEG", exif=exif, **extra)
    return out.getvalue()


def test_the_calibration_gives_focal_lengths_principal_point_and_lens():
    k = xmp_intrinsics(read_metadata(jpeg(SIZE, dji_xmp(FOCAL, CENTRE, SIZE, P4RTK))), SIZE)
    assert k is not None
    assert k.source == "calibration"
    assert (k.fx_px, k.fy_px) == pytest.approx(FOCAL)
    assert (k.cx_px, k.cy_px) == pytest.approx(CENTRE)  # offsets from the photo's centre
    assert k.distortion == P4RTK


def test_a_resized_photo_scales_the_pixels_and_keeps_the_lens():
    """Brought down to a quarter (EXIF keeps the original's size), the focal lengths and the
    principal point's offset shrink fourfold; the distortion, on normalised coordinates, stays."""
    small = (1216, 912)
    original = {T.ExifImageWidth: SIZE[0], T.ExifImageHeight: SIZE[1]}
    k = xmp_intrinsics(
        read_metadata(jpeg(small, dji_xmp(FOCAL, CENTRE, SIZE, P4RTK), original)), small
    )
    assert k is not None
    assert (k.fx_px, k.fy_px) == pytest.approx((FOCAL[0] / 4, FOCAL[1] / 4))
    assert (k.cx_px, k.cy_px) == pytest.approx((608.0 - 7.71 / 4, 456.0 + 45.9 / 4))
    assert k.distortion == P4RTK


def test_a_dewarped_photo_has_no_distortion():
    xmp = dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, dewarped=True)
    k = xmp_intrinsics(read_metadata(jpeg(SIZE, xmp)), SIZE)
    assert k is not None
    assert k.distortion is None
    assert k.fx_px == pytest.approx(FOCAL[0])


def test_the_calibration_may_be_an_element_rather_than_an_attribute():
    numbers = "3659.78,3653.17,-7.71,45.9,-0.269478,0.115681,-0.0000875619,-0.000306177,-0.0357628"
    xmp = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
        'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/">'
        f"<drone-dji:DewarpData>2018-03-13;{numbers}</drone-dji:DewarpData>"
        "</rdf:Description></rdf:RDF></x:xmpmeta>"
    ).encode()
    k = xmp_intrinsics(read_metadata(jpeg(SIZE, xmp)), SIZE)
    assert k is not None
    assert k.distortion is not None
    assert k.distortion.k3 == pytest.approx(-0.0357628)


@pytest.mark.parametrize(
    ("xmp", "size", "tags"),
    [
        # a crop the EXIF betrays: the original's aspect differs
        (
            dji_xmp(FOCAL, CENTRE, SIZE, P4RTK),
            SIZE,
            {T.ExifImageWidth: 4000, T.ExifImageHeight: 4000},
        ),
        (dji_xmp((0.5, 0.5), CENTRE, SIZE, None), SIZE, {}),  # a fov of 180°: not a lens
        (dji_xmp(FOCAL, CENTRE, SIZE, LensDistortion(k1=-0.9)), SIZE, {}),  # folds the photo
        (dji_xmp(FOCAL, CENTRE, SIZE, P4RTK).replace(b"-0.269478000000", b"-5000"), SIZE, {}),
        (dji_xmp(FOCAL, CENTRE, SIZE, P4RTK).replace(b"-0.035762800000", b"nan"), SIZE, {}),
        (
            dji_xmp(FOCAL, CENTRE, SIZE, P4RTK).replace(b",-0.035762800000", b""),
            SIZE,
            {},
        ),  # 8 numbers
        (b"<x:xmpmeta", SIZE, {}),  # broken XML
        (None, SIZE, {}),
    ],
    ids=["crop", "no-lens", "folds", "range", "nan", "eight", "broken", "none"],
)
def test_unusable_or_absent_calibrations_are_not_used(xmp, size, tags):
    assert xmp_intrinsics(read_metadata(jpeg(size, xmp, tags)), size) is None


@settings(max_examples=100, deadline=None)
@given(
    numbers=st.lists(st.floats(-1e7, 1e7), min_size=9, max_size=9)
    | st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=12)
)
def test_any_numbers_in_the_calibration_are_read_or_ignored_never_raised(numbers):
    """Metadata is the photo's, not the user's request: whatever it holds, the reader answers
    intrinsics it checked or nothing."""
    packet = dji_xmp(FOCAL, CENTRE, SIZE, P4RTK)
    start = packet.index(b"2024-05-01;") + len(b"2024-05-01;")
    end = packet.index(b'"', start)
    text = ",".join(repr(v) for v in numbers).encode()
    found = xmp_intrinsics(
        read_metadata(jpeg((64, 48), packet[:start] + text + packet[end:])), (64, 48)
    )
    if found is not None:
        assert found.fx_px is not None
        assert found.fx_px > 0


def test_only_a_jpeg_is_read():
    png = io.BytesIO()
    Image.new("RGB", (64, 48)).save(png, "PNG")
    assert xmp_intrinsics(read_metadata(png.getvalue()), (64, 48)) is None
    assert xmp_intrinsics(read_metadata(b"not an image"), (64, 48)) is None


def test_a_packet_declaring_entities_is_refused_not_expanded():
    """An entity declaration (the start of a billion-laughs bomb) makes the packet unreadable,
    though its calibration would parse: defusedxml refuses it."""
    packet = dji_xmp(FOCAL, CENTRE, SIZE, P4RTK).decode()
    declared = '<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "aaaaaaaaaa">]>' + packet.replace(
        "</rdf:RDF>", "<rdf:li>&a;</rdf:li></rdf:RDF>"
    )
    assert xmp_intrinsics(read_metadata(jpeg(SIZE, packet.encode())), SIZE) is not None
    assert xmp_intrinsics(read_metadata(jpeg(SIZE, declared.encode())), SIZE) is None


def test_an_unreadable_packet_leaves_the_exif_read():
    declared = '<!DOCTYPE x [<!ENTITY a "a">]><x:xmpmeta xmlns:x="adobe:ns:meta/">&a;</x:xmpmeta>'
    metadata = read_metadata(jpeg(SIZE, declared.encode(), {T.FocalLengthIn35mmFilm: 24}))
    assert metadata.xmp == {}
    assert metadata.exif[T.FocalLengthIn35mmFilm] == 24
    assert exif_intrinsics(metadata, SIZE) is not None


def test_the_gimbal_gives_the_camera_s_pitch_and_roll_in_our_conventions():
    """DJI's pitch −90° looks straight down (ours +90°); its roll keeps its sign."""
    xmp = dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(62.5, -3.25))
    assert b'GimbalPitchDegree="-62.50"' in xmp
    assert xmp_attitude(read_metadata(jpeg(SIZE, xmp))) == CameraAttitude(
        pitch_deg=62.5, roll_deg=-3.25
    )


@pytest.mark.parametrize(
    "xmp",
    [
        dji_xmp(FOCAL, CENTRE, SIZE, P4RTK),  # no gimbal
        dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(60.0, 0.0)).replace(
            b'GimbalRollDegree="+0.00" ', b""
        ),  # a pitch alone
        dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(60.0, 0.0)).replace(b"-60.00", b"nan"),
        dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(60.0, 0.0)).replace(b"-60.00", b"-120"),
        None,
    ],
    ids=["none", "pitch-alone", "nan", "beyond-straight-down", "no-xmp"],
)
def test_no_usable_gimbal_is_no_attitude(xmp):
    assert xmp_attitude(read_metadata(jpeg(SIZE, xmp))) is None


@pytest.mark.anyio
@pytest.mark.parametrize(
    ("params", "source"),
    [({"mode": "free"}, "calibration"), ({"mode": "free", "exif": "false"}, None)],
)
async def test_a_free_search_prefers_the_calibration_to_the_exif(controller, params, source):
    _, client = controller
    size = (320, 240)
    original = {T.ExifImageWidth: SIZE[0], T.ExifImageHeight: SIZE[1], T.FocalLengthIn35mmFilm: 24}
    image = jpeg(size, dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(80.0, 1.5)), original)
    search = await submitted_search(client, image, params)
    intrinsics = search["intrinsics"]
    if source is None:  # told not to read the metadata: neither lens nor attitude
        assert intrinsics is None
        assert search["attitude"] is None
        return
    assert search["attitude"] == {"pitch_deg": 80.0, "roll_deg": 1.5}
    assert intrinsics is not None
    assert intrinsics["source"] == source
    assert intrinsics["fx_px"] == pytest.approx(FOCAL[0] * 320 / SIZE[0])
    assert intrinsics["distortion"]["k3"] == pytest.approx(P4RTK.k3)
    assert math.isclose(intrinsics["cx_px"], 160.0 - 7.71 * 320 / SIZE[0])


@pytest.mark.anyio
async def test_a_given_attitude_stands_before_the_gimbal_s(controller):
    _, client = controller
    image = jpeg((320, 240), dji_xmp(FOCAL, CENTRE, SIZE, P4RTK, attitude=(80.0, 1.5)))
    params = {"mode": "free", "attitude": "62.5,-3"}
    search = await submitted_search(client, image, params)
    assert search["attitude"] == {"pitch_deg": 62.5, "roll_deg": -3.0}


@pytest.mark.anyio
@pytest.mark.parametrize(
    "params",
    [
        {"attitude": "60,0"},  # a hemisphere search
        {"mode": "free", "attitude": "95,0"},  # beyond straight down
        {"mode": "free", "attitude": "60,200"},
        {"mode": "free", "attitude": "60"},
        {"mode": "free", "attitude": "1e999,0"},
    ],
)
async def test_a_bad_attitude_is_a_problem_naming_it(controller, params):
    _, client = controller
    answer = await client.post(
        "/searches",
        content=jpeg((320, 240), None),
        params={"scene": "demo", **params},
        headers={"content-type": "image/jpeg"},
    )
    assert answer.status_code == 422, answer.text
    assert answer.headers["content-type"].startswith("application/problem+json")
    assert answer.json()["field"] == "attitude", answer.json()
