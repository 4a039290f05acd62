"""``cosmos search``'s free-camera flags: the photo's lens goes with ``--free`` only (the
search end to end: tests/test_e2e_free.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cosmos.cli import main


@pytest.mark.parametrize(
    "flags",
    [
        ["--fov", "50"],
        ["--intrinsics", "300,300,160,120"],
        ["--distortion", "0,0,0,0"],
        ["--no-exif"],
    ],
)
def test_lens_flags_need_free(tmp_path: Path, capsys: pytest.CaptureFixture[str], flags) -> None:
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"")
    argv = ["search", str(photo), "--scene", "demo", "--url", "http://127.0.0.1:9", *flags]
    assert main(argv) == 2
    assert f"{flags[0]} go with --free" in capsys.readouterr().err
