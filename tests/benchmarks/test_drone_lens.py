"""The drone-lens benchmark's draw (:mod:`benchmarks.drone_lens`): its lenses never fold the
film, and the XMP it writes reads back, through the controller's reader, as the very camera."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from benchmarks.drone_lens import drone_lens
from cosmos.bench.variants import dji_xmp
from services.common.geometry.camera import film_camera
from services.common.geometry.lens import invertible_over_film
from services.controller.photo_metadata import read_metadata
from services.controller.photo_xmp import xmp_intrinsics


@pytest.mark.parametrize("seed", range(20))
def test_a_drawn_lens_reads_back_from_its_xmp(seed):
    width, height, fov = 640, 480, 81.0  # the widest lens the benchmark draws on 45° scenes
    focal, centre, lens = drone_lens(np.random.default_rng(seed), width, height, fov)
    film = film_camera(width, height, (focal, focal), centre)
    assert invertible_over_film(film, lens)
    out = io.BytesIO()
    Image.new("RGB", (width, height)).save(
        out, "JPEG", xmp=dji_xmp((focal, focal), centre, (width, height), lens)
    )
    read = xmp_intrinsics(read_metadata(out.getvalue()), (width, height))
    assert read is not None
    assert (read.fx_px, read.fy_px, read.cx_px, read.cy_px) == pytest.approx(
        (focal, focal, *centre), abs=1e-9
    )
    assert read.distortion is not None
    np.testing.assert_allclose(read.distortion.coefficients(), lens.coefficients(), atol=1e-12)


def test_each_arm_asks_what_it_names():
    """``no lens`` gives the exact intrinsics without the distortion; ``given`` both;
    ``nothing read`` neither, and no EXIF either."""
    from benchmarks.drone_lens import ARMS, LensPhoto, _query
    from services.common.geometry.free_camera import FreeCamera, LensDistortion

    camera = FreeCamera(
        position=(0.0, 0.0, 5.0),
        yaw_deg=0.0,
        pitch_deg=90.0,
        fx_px=500.0,
        fy_px=500.0,
        cx_px=321.0,
        cy_px=239.0,
        distortion=LensDistortion(k1=-0.1),
    )
    photo = LensPhoto("demo", b"xmp", b"exif", camera, 65.0, "nadir", 8.0)
    queries = {arm: _query(photo, arm) for arm in ARMS}
    assert queries["no lens"][1]["intrinsics"] == "500.0,500.0,321.0,239.0"
    assert "distortion" not in queries["no lens"][1]
    assert queries["given"][1]["distortion"].startswith("-0.1,")
    assert queries["nothing read"][1]["exif"] == "false"
    assert "intrinsics" not in queries["nothing read"][1]
    assert queries["EXIF only"][0] == b"exif"
    assert queries["calibration"][0] == b"xmp"


def test_an_unknown_arm_is_refused_before_any_photo_is_made(capsys):
    from benchmarks.drone_lens import main

    with pytest.raises(SystemExit):
        main(["--arms", "EXIF only,bogus"])
    assert "unknown arm(s) bogus" in capsys.readouterr().err
