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
