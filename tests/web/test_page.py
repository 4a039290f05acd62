"""The page in a real browser (Debian's Chromium under Playwright) against the real stack: a full
search from an uploaded target, watched live and replayed; the error paths; the API key asked
once; past searches paged; the broker panel refreshed. The tests write the README's screenshots
(``docs/screenshots/`` when ``SCREENSHOTS_DIR`` says so)."""

from __future__ import annotations

import io
import re
import time

import cv2
import httpx
import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import expect

from tests.web.conftest import SCREENSHOTS, api, render_png

pytestmark = pytest.mark.slow

TIMEOUT_MS = 120_000


def decoded(png: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def colours(png: bytes) -> int:
    """How many distinct colours a screenshot has (a blank canvas has one or two)."""
    return len(np.unique(decoded(png).reshape(-1, 3), axis=0))


def shoot(page, name: str) -> None:
    """A screenshot of the whole page for the README. The viewport is made as tall as the page
    first: Chromium's full-page capture of a taller page scales the canvases wrongly."""
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    size = page.viewport_size
    height = page.evaluate("document.documentElement.scrollHeight")
    page.set_viewport_size({"width": size["width"], "height": height})
    page.wait_for_timeout(300)
    page.screenshot(path=str(SCREENSHOTS / f"{name}.png"))
    page.set_viewport_size(size)


def open_new_search(page, stack, hash_part: str = "#/") -> None:
    page.goto(f"{stack.controller}/{hash_part}")
    page.wait_for_selector("#scene option[value=demo]", state="attached")
    expect(page.locator("#scene-info")).to_contain_text("grid of", timeout=60_000)


def submit(page, target_path, *, strategy: str, theta: str = "", phi: str = "", cap: str = ""):
    page.set_input_files("#target-file", str(target_path))
    page.select_option("#strategy", strategy)
    page.fill("#start_theta_deg", theta)
    page.fill("#start_phi_deg", phi)
    page.fill("#max_iterations", cap)


def changes(page, selector: str, before: bytes, timeout_s: float = 20.0) -> bool:
    """Whether the element's pixels become other than ``before`` (drawing takes a frame or two,
    and a view's image a request)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        now = page.locator(selector).screenshot()
        if not np.array_equal(decoded(now), decoded(before)):
            return True
        page.wait_for_timeout(100)
    return False


def rows(page) -> int:
    return page.locator("#iterations tbody tr").count()


def test_a_full_search_is_watched_live_then_replayed(page, stack, tmp_path):
    target = tmp_path / "target.png"
    target.write_bytes(render_png(stack, "demo", 3, 7))
    open_new_search(page, stack)
    submit(page, target, strategy="simple", theta="75", phi="200")
    expect(page.locator("#target-info")).to_contain_text("320×240")
    expect(page.locator("#preview img")).to_be_visible()  # the scene's preview, for the shot
    page.wait_for_timeout(500)  # and the 3D view's frame (its worker draws it)
    shoot(page, "new-search")
    page.click("#go")
    page.wait_for_url(re.compile(r"#/searches/[0-9a-f-]+$"))
    search_id = page.url.rsplit("/", 1)[1]

    # live: the iterations come in while it runs, the hemisphere and the plot with them
    expect(page.locator("#iterations tbody tr").nth(3)).to_be_attached(timeout=TIMEOUT_MS)
    live_status = page.inner_text("#status")
    expect(page.locator("#view-caption")).to_have_text(re.compile(r"^View \d+:"))
    shoot(page, "live")
    page.wait_for_selector("#status.succeeded", timeout=TIMEOUT_MS)
    assert live_status in {"running", "succeeded"}

    with api(stack) as http:
        final = http.get(f"/searches/{search_id}").json()
    assert final["status"] == "succeeded"
    result = final["result"]
    found = result["pose"]["index"]
    page.wait_for_selector("#result")
    assert f"lat {found['lat']}, lon {found['lon']}" in page.inner_text("#result")
    assert page.inner_text("#renders") == f"{result['renders']} renders"
    # one row per iteration, and (no pose visited twice) one per render
    poses = {(it["pose"]["index"]["lat"], it["pose"]["index"]["lon"]) for it in final["iterations"]}
    assert rows(page) == len(final["iterations"]) == len(poses) == result["renders"]
    assert len(final["iterations"]) >= 4
    timings = page.locator("#iterations tbody tr").first.locator("td").all_inner_texts()
    first = final["iterations"][0]["timings"]
    assert timings[5:] == [
        f"{first['render_ms']:.0f}",
        f"{first['detect_ms']:.0f}",
        f"{first['optimize_ms']:.0f}",
        "—",  # a dense fit is a free search's
        f"{first['total_ms']:.0f}",
    ]
    assert not page.is_visible("#cancel")  # nothing left to cancel

    # the 3D view and the images are drawn, not blank
    assert colours(page.locator("#hemisphere canvas").screenshot()) > 50
    assert colours(page.locator("#target-canvas").screenshot()) > 50

    # the replay slider moves the view: the first view is another image, another caption
    last = len(final["iterations"]) - 1
    expect(page.locator("#view-caption")).to_have_text(re.compile(rf"^View {last}:"))
    page.wait_for_timeout(300)
    at_last = page.locator("#view-canvas").screenshot()
    hemisphere_at_last = page.locator("#hemisphere canvas").screenshot()
    page.locator("#replay").fill("0")
    expect(page.locator("#view-caption")).to_have_text(re.compile(r"^View 0:"))
    assert page.inner_text("#replay-label") == f"iteration 0 of {last}"
    assert changes(page, "#view-canvas", at_last)  # the first view, fetched and drawn
    assert changes(page, "#hemisphere canvas", hemisphere_at_last)  # the path up to view 0
    assert page.locator("#iterations tbody tr.current").get_attribute("data-index") == "0"


def test_a_garbage_upload_shows_the_problem_detail_and_names_the_field(page, stack, tmp_path):
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is no image at all, just words" * 10)
    with api(stack) as http:
        refused = http.post(
            "/searches", files={"image": garbage.read_bytes()}, data={"scene": "demo"}
        )
    assert 400 <= refused.status_code < 500
    detail = refused.json()["detail"]
    open_new_search(page, stack)
    submit(page, garbage, strategy="reprojection")
    page.click("#go")
    error = page.locator("#form-errors [role=alert]")
    error.wait_for()
    assert detail in error.inner_text()
    assert "(field: image)" in error.inner_text()
    assert page.locator("#drop.invalid").count() == 1
    assert "#/searches/" not in page.url  # nothing was started


def test_a_target_without_objects_fails_with_the_detectors_verdict(page, stack, tmp_path):
    blank = tmp_path / "ground.png"
    blank.write_bytes(cv2.imencode(".png", np.full((240, 320, 3), 128, np.uint8))[1].tobytes())
    open_new_search(page, stack)
    submit(page, blank, strategy="reprojection")
    page.click("#go")
    page.wait_for_selector("#status.failed", timeout=TIMEOUT_MS)
    assert "the detector found no objects in the target image" in page.inner_text("#summary")


def test_an_unknown_scene_or_search_in_the_url_says_so(page, stack):
    page.goto(f"{stack.controller}/#/?scene=atlantis")
    alert = page.locator("#scene-message [role=alert]")
    alert.wait_for()
    assert "Unknown scene “atlantis”" in alert.inner_text()
    assert "demo" in alert.inner_text()
    page.goto(f"{stack.controller}/#/?scene=garden")
    expect(page.locator("#scene")).to_have_value("garden")
    assert page.locator("#scene-message [role=alert]").count() == 0
    page.goto(f"{stack.controller}/#/searches/no-such-search")
    missing = page.locator("[role=alert]")
    missing.wait_for()
    assert "No search “no-such-search”" in missing.inner_text()


def test_cancel_ends_a_running_search_as_cancelled(page, stack, tmp_path):
    target = tmp_path / "target.png"
    target.write_bytes(render_png(stack, "demo", 0, 3))
    open_new_search(page, stack)
    submit(page, target, strategy="simple", theta="82.5", phi="180", cap="300")
    page.click("#go")
    page.wait_for_selector("#status.running", timeout=TIMEOUT_MS)
    expect(page.locator("#iterations tbody tr").first).to_be_attached(timeout=TIMEOUT_MS)
    page.click("#cancel")
    page.wait_for_selector("#status.cancelled", timeout=30_000)
    search_id = page.url.rsplit("/", 1)[1]
    with api(stack) as http:
        assert http.get(f"/searches/{search_id}").json()["status"] == "cancelled"
    assert not page.is_visible("#cancel")


def test_the_page_asks_for_the_key_once_and_keeps_it(browser, stack):
    context = browser.new_context()
    try:
        page = context.new_page()
        page.goto(f"{stack.controller}/")
        page.wait_for_selector("#key-dialog[open]")
        page.fill("#key-input", stack.api_key)
        page.click("#key-save")
        page.wait_for_selector("#scene option[value=demo]", state="attached")
        page.reload()
        page.wait_for_selector("#scene option[value=demo]", state="attached")
        assert not page.is_visible("#key-dialog")  # kept in this browser: not asked again
    finally:
        context.close()


def test_the_broker_panel_shows_every_replica_and_keeps_up(page, stack):
    health = httpx.get(f"{stack.controller}/health").json()
    page.goto(f"{stack.controller}/#/searches")
    page.wait_for_selector("table.replicas tbody tr")
    assert page.locator("table.replicas tbody tr").count() == len(health["replicas"])
    assert page.inner_text("#broker-badge") == f"broker {health['status']}"
    served = page.locator("table.replicas tbody tr").first.locator("td[data-field=served]")
    before = int(served.inner_text())
    with api(stack) as http:  # a render the renderer serves: the panel shows it without a reload
        assert http.get("/scenes/demo/view.png", params={"lat": 2, "lon": 1}).status_code == 200
    deadline = time.monotonic() + 10
    while int(served.inner_text()) <= before and time.monotonic() < deadline:
        page.wait_for_timeout(200)
    assert int(served.inner_text()) > before


def test_a_target_made_by_picking_a_pose_on_the_hemisphere_is_found(page, stack):
    open_new_search(page, stack)
    hemisphere = page.locator("#pick-hemisphere canvas")
    hemisphere.wait_for()
    box = hemisphere.bounding_box()
    assert box is not None
    info = page.locator("#target-info")
    # click across the dome until a click lands on a grid pose (a point drawn on it)
    for fy in np.linspace(0.12, 0.6, 13):
        for fx in np.linspace(0.3, 0.7, 9):
            page.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
            try:  # the 3D view's worker says which pose (if any) the click was on
                expect(info).to_have_text(re.compile(r"^Render"), timeout=300)
            except AssertionError:
                continue
            break
        else:
            continue
        break
    expect(info).to_have_text(re.compile(r"^Rendered at lat \d+, lon \d+"), timeout=60_000)
    lat, lon = (int(v) for v in re.findall(r"lat (\d+), lon (\d+)", info.inner_text())[0])
    assert colours(page.locator("#target-preview").screenshot()) > 50
    page.click("#go")
    page.wait_for_url(re.compile(r"#/searches/[0-9a-f-]+$"))
    page.wait_for_selector("#status.succeeded", timeout=TIMEOUT_MS)
    assert page.inner_text("#result").startswith(f"Found: lat {lat}, lon {lon} ")


def turned_jpeg(stored: np.ndarray) -> bytes:
    """``stored`` (BGR) as a JPEG whose EXIF Orientation (6, a camera held upright) says to
    turn it 90° clockwise for display."""
    exif = Image.Exif()
    exif[0x0112] = 6
    out = io.BytesIO()
    Image.fromarray(stored[..., ::-1]).save(out, "JPEG", quality=95, exif=exif.tobytes())
    return out.getvalue()


def test_a_new_search_previews_a_jpeg_its_exif_turns_at_its_stored_size(page, stack, tmp_path):
    """The new-search form states the size the search will decode, and previews the target in
    that shape: a JPEG's stored pixels, not the size the browser reports after its EXIF turn."""
    path = tmp_path / "upright.jpg"
    path.write_bytes(turned_jpeg(decoded(render_png(stack, "demo", 3, 7))))
    open_new_search(page, stack)
    page.set_input_files("#target-file", str(path))
    expect(page.locator("#target-info")).to_contain_text("upright.jpg")
    expect(page.locator("#target-info")).to_contain_text(", 320×240")
    box = page.locator("#target-preview").bounding_box()
    assert box is not None
    assert box["width"] > box["height"], box


def test_a_jpeg_its_exif_turns_is_shown_as_stored_under_its_boxes(page, stack):
    """A JPEG whose EXIF says to turn it (Orientation 6, a camera held upright) is searched as
    its stored pixels, which the detector boxed: the page shows those pixels under the boxes, not
    the picture turned (browsers turn an image by its EXIF unless told not to)."""
    stored = decoded(render_png(stack, "demo", 3, 7))
    with api(stack) as http:
        made = http.post(
            "/searches?scene=demo",
            content=turned_jpeg(stored),
            headers={"Content-Type": "image/jpeg"},
        )
        assert made.status_code in (200, 201, 202), made.text
        search_id = made.json()["id"]
        deadline = time.monotonic() + 60
        while not http.get(f"/searches/{search_id}").json().get("target_detections"):
            assert time.monotonic() < deadline
            time.sleep(0.3)
    page.goto(f"{stack.controller}/#/searches/{search_id}")
    page.wait_for_selector("#target-canvas img:not([hidden])")
    expect(page.locator("#target-canvas .box").first).to_be_attached()
    page.wait_for_timeout(300)
    shot = decoded(page.locator("#target-canvas").screenshot()).astype(np.float32)
    height, width = shot.shape[:2]
    as_stored = cv2.resize(stored, (width, height)).astype(np.float32)
    turned = cv2.resize(cv2.rotate(stored, cv2.ROTATE_90_CLOCKWISE), (width, height))
    off_stored = np.abs(shot - as_stored).mean()
    assert off_stored < 0.5 * np.abs(shot - turned.astype(np.float32)).mean(), off_stored


def test_past_searches_are_listed_a_page_at_a_time_and_open_as_a_replay(page, stack):
    """Last of this module: the searches of the tests above (succeeded, failed, cancelled), and
    as many more as it takes for a search that succeeded and two pages of three."""
    with api(stack) as http:
        listing = http.get("/searches", params={"limit": 200}).json()
        if not any(s["status"] == "succeeded" for s in listing["items"]):
            target = render_png(stack, "demo", 5, 20)
            http.post("/searches?scene=demo", content=target, headers={"Content-Type": "image/png"})
        blank = cv2.imencode(".png", np.full((240, 320, 3), 128, np.uint8))[1].tobytes()
        for _ in range(4 - listing["total"]):  # nothing to search for in these: they fail at once
            http.post("/searches?scene=demo", content=blank, headers={"Content-Type": "image/png"})
        deadline = time.monotonic() + 120
        while True:  # every search finished: the list does not change under the test
            listing = http.get("/searches", params={"limit": 200}).json()
            if all(s["status"] in {"succeeded", "failed", "cancelled"} for s in listing["items"]):
                break
            assert time.monotonic() < deadline, listing
            time.sleep(0.5)
    total = listing["total"]
    page.goto(f"{stack.controller}/#/searches?per=3")
    expect(page.locator("#searches tbody tr")).to_have_count(3)
    assert f"1–3 of {total} (page 1 of {-(-total // 3)})" in page.inner_text(".pager")
    newest = listing["items"][0]
    first_row = page.locator("#searches tbody tr").first.locator("td").all_inner_texts()
    assert first_row[0] == newest["id"][:12]
    assert first_row[1:4] == [newest["status"], newest["scene"], newest["strategy"]]
    assert first_row[4] == (str(newest["result"]["renders"]) if newest["result"] else "—")
    page.click("#older")
    page.wait_for_url(re.compile(r"page=2&per=3$"))
    expect(page.locator("#searches tbody tr")).to_have_count(min(3, total - 3))
    second_page = page.locator("#searches tbody tr td:first-child").all_inner_texts()
    assert second_page == [s["id"][:12] for s in listing["items"][3:6]]
    page.click("#newer")
    expect(page.locator("#searches tbody tr")).to_have_count(3)
    page.goto(f"{stack.controller}/#/searches")
    expect(page.locator("#searches tbody tr")).to_have_count(min(15, total))
    shoot(page, "past-searches")

    # the succeeded search with the most renders opens as a replay, its slider on a middle step
    succeeded = [s for s in listing["items"] if s["status"] == "succeeded"]
    longest = max(succeeded, key=lambda s: s["result"]["renders"])
    page.locator(f"#searches a[href='#/searches/{longest['id']}']").click()
    page.wait_for_selector("#status.succeeded")
    page.wait_for_selector("#result")
    expect(page.locator("#view-caption")).to_have_text(re.compile(r"^View \d+:"))
    middle = longest["result"]["renders"] // 2
    page.locator("#replay").fill(str(middle))
    expect(page.locator("#view-caption")).to_have_text(re.compile(rf"^View {middle}:"))
    page.wait_for_timeout(500)
    shoot(page, "past-search")
