"""A free search from the page in a real browser (Debian's Chromium under Playwright) against the
real stack: a target rendered at a free camera off the hemisphere, its answer's pose in the
panel, its camera drawn as a frustum in the 3D view, the boxes predicted at the answer over the
target; the camera's pitch and roll typed in, recorded and shown, and refused on their field when
out of range; a lens's distortion typed in, used and shown. It writes the README's
``free-search`` screenshot (``SCREENSHOTS_DIR``)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from playwright.sync_api import expect

from cosmos.bench.variants import exif_jpeg
from services.common.geometry.free_camera import (
    FreeCamera,
    LensDistortion,
    yaw_pitch_roll_of_rotation,
)
from services.renderer.client import RendererClient
from tests.web.conftest import api
from tests.web.test_page import TIMEOUT_MS, colours, decoded, open_new_search, shoot

pytestmark = pytest.mark.slow

DRONE = FreeCamera(position=(-3.5, 3.0, 4.5), look_at=(0.3, -0.4, 0.0), roll_deg=12.0)
"""|position| ≈ 6.4, inside the hemisphere (radius 8): 45° down, rolled, looking past the centre."""
ANSWER_RGB = (255, 77, 79)  # the answer's frustum (hemisphere-scene.js, COLOURS.answer): unlit


def fixed(values, digits: int) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def free_search(
    page,
    stack,
    target,
    camera: FreeCamera,
    *,
    give_fov: bool,
    exif: int | None = None,
    read_exif: bool = True,
    attitude: str = "",
    distortion: str = "",
) -> dict:
    """A free search from the page for ``camera`` rendered (its fov given or not; a JPEG whose
    EXIF says ``exif`` mm as FocalLengthIn35mmFilm when given, read or not; ``attitude`` and
    ``distortion`` typed into their fields), once it succeeded: the search as the API has it."""
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, truth = renderer.render_camera("demo", camera)
    target.write_bytes(image if exif is None else exif_jpeg(image, exif))
    open_new_search(page, stack)
    page.set_input_files("#target-file", str(target))
    assert page.is_disabled("#fov_deg")  # a lens and an attitude are for free searches only
    assert page.is_disabled("#attitude")
    assert page.is_disabled("#distortion")
    assert page.is_disabled("#exif")
    page.select_option("#mode", "free")
    assert page.is_disabled("#strategy")
    assert page.is_disabled("#start_theta_deg")
    assert page.is_checked("#exif")  # the EXIF is read unless unticked
    if give_fov:
        page.fill("#fov_deg", f"{truth.camera.fov_deg}")
    if not read_exif:
        page.uncheck("#exif")
    page.fill("#attitude", attitude)
    page.fill("#distortion", distortion)
    page.click("#go")
    page.wait_for_url(re.compile(r"#/searches/[0-9a-f-]+$"))
    search_id = page.url.rsplit("/", 1)[1]
    page.wait_for_selector("#status.succeeded", timeout=TIMEOUT_MS)
    page.wait_for_selector("#free-answer")
    with api(stack) as http:
        return http.get(f"/searches/{search_id}").json()


def test_a_free_search_shows_its_camera_its_pose_and_the_predicted_boxes(page, stack, tmp_path):
    _, pitch, roll = yaw_pitch_roll_of_rotation(DRONE.rotation())
    attitude = f"{pitch:.1f}, {roll:.1f}"  # as a flight log has the gimbal's
    target = tmp_path / "drone.png"
    final = free_search(page, stack, target, DRONE, give_fov=True, attitude=attitude)
    assert final["mode"] == "free"
    assert final["attitude"] == {"pitch_deg": round(pitch, 1), "roll_deg": round(roll, 1)}
    assert page.inner_text("#search-attitude").startswith(
        f"camera's pitch {round(pitch, 1):g}°, roll {round(roll, 1):g}°"
    )
    free = final["result"]["free"]
    pose = free["pose"]

    def field(name: str) -> str:
        return page.inner_text(f"#free-answer td[data-field={name}]")

    assert field("status") == free["status"] == "found"
    assert field("position") == fixed(pose["position"], 3)
    assert field("yaw-pitch-roll") == f"{fixed(pose['yaw_pitch_roll_deg'], 2)}°"
    assert field("fov").startswith(f"{pose['intrinsics']['fov_deg']:.2f}°, given ")
    assert field("residual").startswith(f"{pose['residual_px']:.2f} px")
    assert field("renders") == str(free["renders"]) == "1"
    assert page.inner_text("#renders") == f"{final['result']['renders']} renders"
    assert page.inner_text("#result").startswith("Found: camera at (")
    expect_view = f"free camera at ({fixed(final['iterations'][0]['camera']['position'], 2)})"
    assert expect_view in page.inner_text("#view-caption")
    # the iteration's row says what its dense fit took, beside its detection
    timings = final["iterations"][0]["timings"]
    assert timings["refine_ms"] > 0
    cells = page.locator("#iterations tbody tr").first.locator("td").all_inner_texts()
    assert cells[8] == f"{timings['refine_ms']:.0f}"
    assert cells[9] == f"{timings['total_ms']:.0f}"

    # the target with the boxes predicted at the answer, beside the detected ones
    predicted = [c for c in pose["correspondences"] if c["predicted_box"] is not None]
    assert len(predicted) >= 4
    target_view = page.locator("#target-canvas")
    assert target_view.get_attribute("data-predicted") == str(len(predicted))
    assert target_view.locator(".box.predicted").count() == len(predicted)
    detected = len(final["target_detections"])
    assert target_view.locator(".box:not(.predicted)").count() == detected

    # the 3D view: the view rendered (at the box pose) and the answer's frustum (that pose
    # refined densely by the same render)
    hemisphere = page.locator("#hemisphere")
    assert free["box_pose"] is not None
    assert hemisphere.get_attribute("data-frusta") == "2"
    assert final["iterations"][0]["camera"]["position"] == free["box_pose"]["position"]
    page.wait_for_timeout(500)  # the worker's frame
    shot = page.locator("#hemisphere canvas").screenshot()
    assert colours(shot) > 50
    drawn = decoded(shot)
    near_answer = np.all(np.abs(drawn[:, :, ::-1].astype(int) - ANSWER_RGB) <= 40, axis=2)
    # the frustum's red lines are drawn (the lit red ball stays > 80 away: at most (169, 54, 54))
    assert near_answer.sum() > 60, near_answer.sum()
    shoot(page, "free-search")


def test_a_photo_s_exif_focal_length_is_read_unless_unticked(page, stack, tmp_path):
    """The demo scene's camera (45° over 320 × 240) is a 42 mm lens in 35 mm terms."""
    read = free_search(page, stack, tmp_path / "drone.jpg", DRONE, give_fov=False, exif=42)
    intrinsics = read["intrinsics"]
    assert intrinsics["source"] == "exif"
    assert read["result"]["free"]["pose"]["intrinsics"]["source"] == "exif"
    assert "from the photo's EXIF" in page.inner_text("#free-answer td[data-field=fov]")
    unread = free_search(
        page, stack, tmp_path / "drone.jpg", DRONE, give_fov=False, exif=42, read_exif=False
    )
    assert unread["intrinsics"] is None
    assert unread["result"]["free"]["pose"]["intrinsics"]["source"] == "estimated"


def test_an_ambiguous_free_answer_shows_its_alternatives(page, stack, tmp_path):
    """Three objects seen, no lens given: the pose is not pinned, the answer is ambiguous and
    its alternatives are drawn beside it."""
    camera = FreeCamera(
        position=(1.2, -3.5, 3.0), look_at=(0.6, -0.7, 0.3), fov_deg=40, roll_deg=10
    )
    final = free_search(page, stack, tmp_path / "few.png", camera, give_fov=False)
    free = final["result"]["free"]
    assert free["status"] == "ambiguous"
    assert not final["result"]["confirmed"]
    assert free["alternatives"]
    assert page.inner_text("#result").startswith("Best pose (ambiguous, not confirmed): ")
    assert page.inner_text("#free-answer td[data-field=status]") == "ambiguous"
    listed = page.inner_text("#free-answer td[data-field=alternatives]")
    assert listed.count(" px") == len(free["alternatives"])
    source = free["pose"]["intrinsics"]["source"]
    assert source in {"estimated", "scene"}
    assert page.inner_text("#result").count(f"({source})") == 1
    # the answer and each alternative a frustum, and each view rendered that is neither (the
    # box pose a dense fit moved the answer from, a candidate's own render before the one at
    # its dense fit)
    candidates = {tuple(p["position"]) for p in (free["pose"], *free["alternatives"])}
    cameras = [it["camera"] for it in final["iterations"]]
    cameras += [it["candidate_camera"] for it in final["iterations"] if it["candidate_camera"]]
    views = {tuple(c["position"]) for c in cameras} - candidates
    frusta = len(views) + 1 + len(free["alternatives"])
    assert page.locator("#hemisphere").get_attribute("data-frusta") == str(frusta)

    # the past searches name a free search's method, not a strategy it never used
    page.goto(f"{stack.controller}/#/searches")
    row = page.locator("#searches tbody tr", has_text=final["id"][:12])
    expect(row.locator("td").nth(3)).to_have_text("free camera")


def test_a_lens_distortion_typed_in_is_used_and_shown(page, stack, tmp_path):
    """A photo through a barrel lens, its fov and distortion typed in: the search takes both, as
    given, confirms the pose, and its facts line says what lens it was given."""
    lens = LensDistortion(k1=-0.1)
    camera = DRONE.model_copy(update={"fov_deg": 60.0, "distortion": lens})
    final = free_search(
        page, stack, tmp_path / "wide.png", camera, give_fov=True, distortion="-0.1, 0, 0, 0"
    )
    assert final["intrinsics"]["distortion"]["k1"] == -0.1
    k = final["result"]["free"]["pose"]["intrinsics"]
    assert k["source"] == "given"
    assert k["distortion"]["k1"] == -0.1
    assert final["result"]["confirmed"], final["result"]["reason"]
    expect(page.locator("#search-lens")).to_contain_text(
        "°, distortion k1 -0.1, k2 0, p1 0, p2 0, k3 0"
    )


def test_an_attitude_out_of_range_is_refused_on_its_field(page, stack, tmp_path):
    with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
        image, _ = renderer.render_camera("demo", DRONE)
    (tmp_path / "drone.png").write_bytes(image)
    open_new_search(page, stack)
    page.set_input_files("#target-file", str(tmp_path / "drone.png"))
    page.select_option("#mode", "free")
    page.fill("#attitude", "95, 0")  # beyond straight down
    page.click("#go")
    expect(page.locator("#form-errors")).to_contain_text("(field: attitude)")
    expect(page.locator("#attitude")).to_have_class(re.compile(r"\binvalid\b"))
    assert page.url.endswith("#/")  # no search was made
