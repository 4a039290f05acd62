"""End to end, a free-camera search: the four real services as separate processes on loopback
(real renderer, real ONNX detector, real HTTP), a target rendered at a camera off the
hemisphere (lower than its radius, looking down past the centre, rolled), searched with
``mode=free`` through the controller's public API: one render confirms the box pose and refines
it densely (closer to the truth than the boxes put it)."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest

from cosmos.bench.variants import dji_xmp, exif_jpeg
from cosmos.cli import main
from cosmos.stack import Stack
from services.common.auth import bearer
from services.common.contracts.render import PoseQuery, RenderRequest
from services.common.contracts.search import Search
from services.common.geometry.free_camera import (
    FreeCamera,
    LensDistortion,
    yaw_pitch_roll_of_rotation,
)
from services.common.geometry.pose import GridIndex
from services.controller.client import ControllerClient
from services.controller.settings import ControllerSettings
from services.renderer.client import RendererClient
from tests.support import e2e_stack

pytestmark = pytest.mark.slow

RADIUS = 8.0  # the demo scene's hemisphere radius
DRONE = FreeCamera(position=(-3.5, 3.0, 4.5), look_at=(0.3, -0.4, 0.0), roll_deg=12.0)
"""|position| ≈ 6.4 < 8: inside the hemisphere, 45° down, looking past the scene's centre."""


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with e2e_stack(tmp_path_factory.mktemp("stack")) as running:
        yield running


def search_for(stack: Stack, image: bytes, **options) -> Search:
    with ControllerClient(stack.controller, api_key=stack.api_key) as client:
        search = client.submit(image, "demo", mode="free", **options)
        for _ in client.follow(search.id, timeout_s=120):
            pass
        return client.get(search.id)


def pixels(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def rotation_error_deg(quaternion_wxyz, truth: FreeCamera) -> float:
    found = FreeCamera(position=(0.0, 0.0, 1.0), quaternion_wxyz=quaternion_wxyz).rotation()
    relative = found.T @ truth.rotation()
    return math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))


def test_a_free_camera_is_found_through_the_services(stack):
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    final = search_for(stack, image, fov_deg=truth.camera.fov_deg)
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    free = result.free
    assert free is not None
    assert free.status == "found", result.reason
    assert result.confirmed
    assert result.renders == 1
    assert math.dist(free.pose.position, DRONE.position) < 0.05 * RADIUS
    assert rotation_error_deg(free.pose.quaternion_wxyz, DRONE) < 3.0
    # the render that confirmed the box pose refined it densely: closer to the truth
    assert free.dense is not None
    assert free.dense.accepted, free.dense
    assert free.box_pose is not None
    refined = math.dist(free.pose.position, DRONE.position)
    boxes = math.dist(free.box_pose.position, DRONE.position)
    assert refined < boxes
    assert refined < 0.01 * RADIUS
    assert rotation_error_deg(free.pose.quaternion_wxyz, DRONE) < rotation_error_deg(
        free.box_pose.quaternion_wxyz, DRONE
    )
    assert free.pose.yaw_pitch_roll_deg[2] == pytest.approx(12.0, abs=3.0)
    assert free.pose.intrinsics.source == "given"
    assert free.pose.intrinsics.fov_deg == pytest.approx(truth.camera.fov_deg)
    assert len(free.pose.correspondences) >= 4
    # the grid pose nearest the camera's direction from the scene centre: θ 45°, φ ≈ 139°
    assert free.nearest_grid == result.pose
    assert abs(result.pose.theta_deg - 45.3) <= 7.5
    assert abs(result.pose.phi_deg - 139.4) <= 7.5
    (iteration,) = final.iterations
    assert iteration.camera is not None
    assert iteration.done
    # the iteration's view is its camera rendered again, identically
    with httpx.Client(base_url=stack.controller, headers=bearer(stack.api_key)) as http:
        view = http.get(f"/searches/{final.id}/iterations/0/view.png")
    assert view.status_code == 200, view.text
    spp = ControllerSettings.model_fields["controller_view_spp"].default
    width, height = iteration.image_size
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        direct, _ = renderer.render_camera(
            "demo", iteration.camera, width=width, height=height, spp=spp
        )
    assert np.array_equal(pixels(view.content), pixels(direct))


def test_a_48_megapixel_drone_jpeg_is_found(stack):
    """A drone camera's photo, 8064 x 6048 (48 MP; stood in for by a 2048 x 1536 render
    enlarged): the services' limits used to refuse anything over 16.8 MP."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE, width=2048, height=1536, spp=16)
    photo = cv2.resize(pixels(image), (8064, 6048), interpolation=cv2.INTER_LINEAR)
    ok, jpeg = cv2.imencode(".jpg", photo, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    final = search_for(stack, jpeg.tobytes(), fov_deg=truth.camera.fov_deg)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    free = final.result.free
    assert free is not None
    assert free.status == "found", final.result.reason
    assert final.result.renders == 1
    assert math.dist(free.pose.position, DRONE.position) < 0.02 * RADIUS
    assert rotation_error_deg(free.pose.quaternion_wxyz, DRONE) < 1.0
    # the answer is in the photo's own pixels
    assert free.pose.intrinsics.cx_px == pytest.approx(4032.0)
    assert free.pose.intrinsics.cy_px == pytest.approx(3024.0)


def test_without_intrinsics_the_focal_length_is_estimated_and_said_so(stack):
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    final = search_for(stack, image)
    assert final.status == "succeeded", final.error
    assert final.result is not None
    free = final.result.free
    assert free is not None
    assert free.status == "found", final.result.reason
    assert free.pose.intrinsics.source == "estimated"
    assert free.pose.intrinsics.fov_deg == pytest.approx(truth.camera.fov_deg, rel=0.03)
    assert math.dist(free.pose.position, DRONE.position) < 0.05 * RADIUS
    assert final.result.renders == 1
    # the focal length fitted with the pose by the render's edges (measured: 45.07° for 45°)
    assert free.dense is not None
    assert free.dense.accepted, free.dense
    assert free.dense.focal_fitted
    assert free.box_pose is not None
    assert free.pose.intrinsics.fov_deg == pytest.approx(truth.camera.fov_deg, rel=0.005)
    assert math.dist(free.pose.position, DRONE.position) < math.dist(
        free.box_pose.position, DRONE.position
    )


def test_a_photo_s_exif_focal_length_is_used_and_said_so(stack):
    """The camera's EXIF, as a camera writes it (whole millimetres), stands for the fov."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    k = truth.camera
    focal_35mm = round(k.fx * math.hypot(36.0, 24.0) / math.hypot(k.width, k.height))
    final = search_for(stack, exif_jpeg(image, focal_35mm))
    assert final.status == "succeeded", final.error
    assert final.result is not None
    free = final.result.free
    assert free is not None
    # found from the boxes, its render agrees, but no render can check an EXIF focal length
    assert free.status == "ambiguous", final.result.reason
    assert not final.result.confirmed
    assert "focal length from the photo's EXIF" in final.result.reason
    assert "no render can check the photo's EXIF focal length" in final.result.reason
    assert free.pose.intrinsics.source == "exif"
    assert free.pose.intrinsics.fx_px == pytest.approx(k.fx, rel=0.02)  # the rounding only
    assert math.dist(free.pose.position, DRONE.position) < 0.02 * RADIUS
    assert rotation_error_deg(free.pose.quaternion_wxyz, DRONE) < 1.0
    assert final.result.renders == 1
    assert free.dense is not None
    assert not free.dense.focal_fitted
    # told not to, the search estimates the focal length from the boxes
    unread = search_for(stack, exif_jpeg(image, focal_35mm), exif="false")
    assert unread.result is not None
    assert unread.result.free is not None
    assert unread.result.free.pose.intrinsics.source == "estimated"


def test_a_drone_s_calibration_in_its_xmp_is_used_as_given(stack):
    """A survey drone's photo through a wide, barrel-distorted lens, its calibration in the XMP
    (DJI's DewarpData) beside a nominal EXIF focal length: the search takes the calibration, as
    if given, and confirms the pose; with the EXIF's focal length alone the lens is estimated
    from the edges and the pose refitted by a render through it (measured first: ``k1`` −0.097,
    1 % of the radius off, before that render), and not confirmed."""
    lens = LensDistortion(k1=-0.12, k2=0.02, p1=2e-4, p2=-3e-4, k3=-0.003)
    focal = 640 / (2 * math.tan(math.radians(35.0)))  # 70° across 640 pixels
    centre = (324.0, 237.0)
    camera = DRONE.model_copy(
        update={"fx_px": focal, "fy_px": focal, "cx_px": centre[0], "cy_px": centre[1]}
        | {"distortion": lens}
    )
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, _ = renderer.render_camera("demo", camera, width=640, height=480, spp=16)
    nominal = round(focal * math.hypot(36.0, 24.0) / 800.0)
    _, pitch, roll = yaw_pitch_roll_of_rotation(DRONE.rotation())
    gimbal = (pitch + 0.4, roll - 0.3)  # a gimbal's angles are good to about a degree
    xmp = dji_xmp((focal, focal), centre, (640, 480), lens, attitude=gimbal)
    final = search_for(stack, exif_jpeg(image, nominal, xmp=xmp))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    free = result.free
    assert free is not None
    k = free.pose.intrinsics
    assert k.source == "calibration"
    assert final.attitude is not None
    assert (final.attitude.pitch_deg, final.attitude.roll_deg) == pytest.approx(gimbal, abs=0.01)
    assert (k.cx_px, k.cy_px) == pytest.approx(centre)
    assert k.distortion == lens
    assert free.status == "found", result.reason
    assert result.confirmed, result.reason
    assert "the drone's calibration" in result.reason
    calibrated = math.dist(free.pose.position, DRONE.position)
    assert calibrated < 0.01 * RADIUS
    assert rotation_error_deg(free.pose.quaternion_wxyz, DRONE) < 1.0
    # the EXIF's focal length alone, no lens: the fit's lens check sees the bend, and the
    # answer is the pose fitted with the k1 it estimates from a render through it, never
    # confirmed
    exif_only = search_for(stack, exif_jpeg(image, nominal))
    unlensed = exif_only.result
    assert unlensed is not None
    assert unlensed.free is not None
    assert not unlensed.confirmed
    assert unlensed.free.status == "ambiguous"
    assert "the photo's edges bend as a distorting lens's do" in unlensed.reason
    estimated = unlensed.free.pose.intrinsics
    assert estimated.source == "estimated"
    assert estimated.distortion is not None
    assert -0.16 < estimated.distortion.k1 < -0.08  # the lens's own k1 is -0.12
    assert unlensed.free.dense is not None
    assert unlensed.free.dense.lens is not None
    assert unlensed.free.dense.lens.bends
    assert math.dist(unlensed.free.pose.position, DRONE.position) < 0.03 * RADIUS
    assert "refitted through the estimated lens by one more render" in unlensed.reason
    assert unlensed.renders == 2


def test_a_pose_the_photo_s_gimbal_contradicts_is_not_answered(stack):
    """The XMP's gimbal says the camera looked 30° steeper than it did (a scene whose ground is
    not level, say): no pose that explains the boxes has that attitude, and the answer says
    so, unconfirmed, with the boxes' pose and the photo's angles."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    k = truth.camera
    _, pitch, roll = yaw_pitch_roll_of_rotation(DRONE.rotation())
    xmp = dji_xmp(
        (k.fx, k.fy), (k.cx, k.cy), (k.width, k.height), None, attitude=(pitch + 30, roll)
    )
    final = search_for(stack, exif_jpeg(image, 35, xmp=xmp))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    assert result.free is not None
    assert not result.confirmed
    assert result.free.status == "ambiguous"
    assert f"pitch and roll the photo states ({pitch + 30:.1f}°" in result.reason, result.reason
    assert result.free.pose.intrinsics.source == "calibration"
    assert math.dist(result.free.pose.position, DRONE.position) < 0.05 * RADIUS


def test_an_exif_focal_length_the_image_refutes_is_overruled(stack):
    """The EXIF states a focal length 15 % long (a crop it does not say): the search does not
    keep it, the render's edges fit the true one, and the answer says so, unconfirmed."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    k = truth.camera
    focal_35mm = round(1.15 * k.fx * math.hypot(36.0, 24.0) / math.hypot(k.width, k.height))
    final = search_for(stack, exif_jpeg(image, focal_35mm))
    assert final.status == "succeeded", final.error
    result = final.result
    assert result is not None
    free = result.free
    assert free is not None
    assert not result.confirmed
    assert free.status == "ambiguous"
    assert "do not bear out the photo's EXIF focal length" in result.reason, result.reason
    assert free.pose.intrinsics.source == "estimated"
    assert free.pose.intrinsics.fx_px == pytest.approx(k.fx, rel=0.02)
    assert math.dist(free.pose.position, DRONE.position) < 0.02 * RADIUS
    assert free.box_pose is not None  # the EXIF's pose, 15 % along the axis
    assert math.dist(free.box_pose.position, DRONE.position) > 0.05 * RADIUS
    assert result.renders == 1


def test_cosmos_search_free_prints_the_answer(stack, tmp_path, monkeypatch, capsys):
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", DRONE)
    photo = tmp_path / "drone.png"
    photo.write_bytes(image)
    monkeypatch.setenv("COSMOS_API_KEY", stack.api_key)
    argv = ["search", str(photo), "--scene", "demo", "--free", "--fov", "45"]
    argv += ["--url", stack.controller, "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "queued: any camera on demo" in printed
    assert "\nfound: confidence" in printed
    assert "intrinsics given: fov 45.00°" in printed
    assert "yaw/pitch/roll" in printed
    assert "nearest grid pose: lat" in printed
    assert len(list((tmp_path / "out").glob("search-*-trajectory.png"))) == 1
    # a camera's JPEG: its EXIF focal length (the camera's, as a camera writes it), unless
    # told not to read it
    k = truth.camera
    photo = tmp_path / "drone.jpg"
    photo.write_bytes(
        exif_jpeg(image, round(k.fx * math.hypot(36.0, 24.0) / math.hypot(k.width, k.height)))
    )
    argv = ["search", str(photo), "--scene", "demo", "--free", "--url", stack.controller]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    assert "intrinsics exif: fov" in capsys.readouterr().out
    assert main([*argv, "--no-exif", "--out", str(tmp_path / "out")]) == 0
    assert "intrinsics estimated: fov" in capsys.readouterr().out


def test_cosmos_search_takes_a_flight_of_photos_and_writes_their_poses(
    stack, tmp_path, monkeypatch, capsys
):
    """Several photos: each searched (two at a time), a line said per photo, the answers
    written as a CSV row each in the order given; a photo that cannot be read or that the
    controller refuses keeps its row, saying why, and the others are answered all the same."""
    second = FreeCamera(position=(4.0, -2.5, 3.5), look_at=(-0.5, 0.5, 0.0), roll_deg=-8.0)
    photos = []
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        for name, camera in (("first.png", DRONE), ("second.png", second)):
            image, _ = renderer.render_camera("demo", camera)
            photos.append(tmp_path / name)
            photos[-1].write_bytes(image)
    (tmp_path / "notes.png").write_bytes(b"not an image at all")
    photos[1:1] = [tmp_path / "missing.png", tmp_path / "notes.png"]
    table = tmp_path / "flight" / "poses.csv"
    monkeypatch.setenv("COSMOS_API_KEY", stack.api_key)
    argv = ["search", *map(str, photos), "--scene", "demo", "--free", "--fov", "45"]
    assert main([*argv, "--url", stack.controller, "--poses", str(table)]) == 3
    said = capsys.readouterr().out.splitlines()
    images = [line.split(": ")[0] for line in said[:4]]
    # the unsearched at once (the second worker's), the searched as they end
    assert images[:2] == [str(photos[1]), str(photos[2])]
    assert sorted(images[2:]) == sorted([str(photos[0]), str(photos[3])])
    assert said[0].endswith("not searched: cannot be read (No such file or directory)")
    assert "not searched: refused (4" in said[1]
    assert said[4] == f"wrote {table}: 4 photo(s)"
    with table.open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [row["image"] for row in rows] == list(map(str, photos))
    for row, truth in ((rows[0], DRONE), (rows[3], second)):
        assert row["status"] == "succeeded"
        assert row["answer"] == "found"
        assert row["confirmed"] == "True"
        position = tuple(float(row[axis]) for axis in "xyz")
        assert math.dist(position, truth.position) < 0.03 * RADIUS, row
        quaternion = tuple(float(row[q]) for q in ("qw", "qx", "qy", "qz"))
        assert rotation_error_deg(quaternion, truth) < 1.0, row
        assert float(row["fov_deg"]) == pytest.approx(45.0)
        assert row["intrinsics"] == "given"
        assert int(row["renders"]) >= 1
    for row in rows[1:3]:
        assert row["status"] == "not searched"
        assert row["x"] == row["search_id"] == ""
        assert row["reason"]
    # one hemisphere photo: followed as it runs, and its row holds its hemisphere pose
    target = RenderRequest(scene="demo", pose=PoseQuery(lat=3, lon=7))
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image = renderer.render_png(target)
        truth = renderer.scene("demo").spec.search.grid().pose(GridIndex(lat=3, lon=7))
    photo = tmp_path / "hemisphere.png"
    photo.write_bytes(image)
    argv = ["search", str(photo), "--scene", "demo", "--url", stack.controller]
    assert main([*argv, "--out", str(tmp_path / "out"), "--poses", str(table)]) == 0
    assert "queued: reprojection on demo" in capsys.readouterr().out
    with table.open(newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert row["status"] == "succeeded"
    assert row["answer"] == "found"
    assert row["x"] == ""
    assert float(row["theta_deg"]) == pytest.approx(truth.theta_deg, abs=1.0)
    assert float(row["phi_deg"]) == pytest.approx(truth.phi_deg, abs=1.0)
