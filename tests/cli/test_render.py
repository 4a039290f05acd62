"""``cosmos render`` with a free camera: rendered in process on a small film, its ground truth
agrees with the camera asked for, and every bad flag is one line on stderr and a non-zero exit."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cosmos.cli import main
from cosmos.cli import render as render_cli
from services.common.geometry.free_camera import quaternion_of_rotation
from services.renderer.client import RendererError

FILM = ["--width", "96", "--height", "72", "--spp", "2"]


def test_free_camera_renders_with_its_ground_truth(tmp_path: Path) -> None:
    out, ann = tmp_path / "view.png", tmp_path / "view.json"
    argv = ["render", "--scene", "demo", "--position", "-4,0,3", "--look-at", "0,0,0.4"]
    argv += ["--roll", "10", "--fov", "50", *FILM, "-o", str(out), "--annotations", str(ann)]
    assert main(argv) == 0
    image = cv2.imread(str(out))
    assert image is not None
    assert image.shape == (72, 96, 3)
    truth = json.loads(ann.read_text())
    assert truth["pose"] is None
    assert truth["camera"]["position"] == pytest.approx([-4.0, 0.0, 3.0])
    assert truth["camera"]["fov_deg"] == pytest.approx(50.0)
    assert any(obj["visible_fraction"] > 0.5 for obj in truth["objects"])


def test_intrinsics_and_distortion_reach_the_camera(tmp_path: Path) -> None:
    ann = tmp_path / "view.json"
    argv = ["render", "--position", "0,0,6", "--ypr", "30,90,0"]
    argv += ["--intrinsics", "90,88,47,37", "--distortion", "-0.05,0.01,0,0,0.002", *FILM]
    argv += ["-o", str(tmp_path / "v.png"), "--annotations", str(ann)]
    assert main(argv) == 0
    truth = json.loads(ann.read_text())
    camera = truth["camera"]
    assert (camera["fx"], camera["fy"], camera["cx"], camera["cy"]) == (90, 88, 47, 37)
    assert truth["distortion"] == {"k1": -0.05, "k2": 0.01, "p1": 0.0, "p2": 0.0, "k3": 0.002}
    forward = np.asarray(camera["rotation"])[2]  # world-to-camera: row 2 is the optical axis
    assert forward == pytest.approx([0.0, 0.0, -1.0], abs=1e-9)


def test_quaternion_ypr_and_look_at_give_the_same_camera() -> None:
    by_angles = render_cli.free_camera_of_args(_flags(position="0,0,1", ypr="30,20,10"))
    q = ",".join(repr(v) for v in quaternion_of_rotation(by_angles.rotation()))
    by_quaternion = render_cli.free_camera_of_args(_flags(position="0,0,1", quaternion=q))
    assert by_quaternion.rotation() == pytest.approx(by_angles.rotation(), abs=1e-12)
    ahead = np.array([0.0, 0.0, 1.0]) + by_angles.rotation()[:, 2]
    at = ",".join(repr(float(v)) for v in ahead)
    by_look_at = render_cli.free_camera_of_args(_flags(position="0,0,1", look_at=at, roll=10.0))
    assert by_look_at.rotation() == pytest.approx(by_angles.rotation(), abs=1e-9)


def _flags(**given: object) -> argparse.Namespace:
    """The free-camera flags as parsed, ``given`` set and the rest left out."""
    names = ("ypr", "look_at", "quaternion", "roll", "fov", "intrinsics", "distortion")
    return argparse.Namespace(**(dict.fromkeys(names) | given))


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--position", "1,2", "--ypr", "0,90,0"], "--position takes 3 comma-separated numbers"),
        (["--position", "0,0,5", "--ypr", "0,nan,0"], "--ypr takes finite numbers"),
        (["--position", "0,0,5", "--ypr", "a,b,c"], "--ypr takes 3 comma-separated numbers"),
        (
            ["--position", "0,0,5", "--ypr", "0,90,0", "--fov", "60", "--distortion", "0,0,0"],
            "--distortion takes 4 or 5 comma-separated numbers",
        ),
        (["--position", "0,0,5"], "exactly one of --ypr, --look-at and --quaternion"),
        (["--position", "0,0,5", "--ypr", "0,90,0", "--look-at", "0,0,0"], "exactly one of"),
        (["--position", "0,0,5", "--quaternion", "0,0,0,0"], "zero length"),
        (["--position", "0,0,5", "--ypr", "0,90,0", "--fov", "200"], "fov_deg"),
        (["--position", "0,0,5", "--ypr", "0,90,0", "--roll", "3"], "--roll goes with --look-at"),
        (["--position", "0,0,5", "--ypr", "0,90,0", "--theta", "30"], "drop --theta"),
        (["--fov", "30"], "--fov needs a free camera"),
        (["--position", "0,0,-1", "--ypr", "0,90,0"], "not above the ground"),
        (["--position", "1.2,-0.6,0.45", "--ypr", "0,0,0"], "inside the bounding box"),
    ],
)
def test_bad_flags_say_one_line(
    flags: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status = main(["render", *flags, *FILM, "-o", str(tmp_path / "v.png")])
    err = capsys.readouterr().err
    assert status != 0
    assert message in err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert not (tmp_path / "v.png").exists()


def test_a_renderers_422_is_one_line(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    class Refusing:
        def __init__(self, *args: object, **kwargs: object) -> None:
            pass

        def __enter__(self) -> Refusing:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def render_png(self, request: object) -> bytes:
            raise RendererError("renderer", 422, "the camera stands inside object 0")

    monkeypatch.setattr(render_cli, "RendererClient", Refusing)
    argv = ["render", "--position", "0,0,5", "--ypr", "0,90,0", "--url", "http://renderer"]
    assert main([*argv, "-o", str(tmp_path / "v.png")]) == 1
    err = capsys.readouterr().err
    assert err.strip() == "cosmos: renderer answered 422: the camera stands inside object 0"


def test_help_lists_the_free_camera(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["render", "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--position", "--ypr", "--look-at", "--roll", "--quaternion", "--fov"):
        assert flag in text
    assert "--intrinsics" in text
    assert "--distortion" in text
