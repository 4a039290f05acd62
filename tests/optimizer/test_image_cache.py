"""The cache of what planning makes of each image of a request: a search's requests resend
their whole history as new JSON, and each image must be processed once, found again by
content, bounded, and never change an answer or an error."""

from __future__ import annotations

import json

import pytest

from services.common.contracts.optimize import (
    ImageDetections,
    NextPoseRequest,
    NextPoseResponse,
    TargetImage,
    VisitedView,
)
from services.common.errors import UnprocessableError
from services.common.geometry.grid import grid_for
from services.common.geometry.pose import GridIndex
from services.common.geometry.scene import CameraSpec
from services.optimizer.calibration import CalibrationStore
from services.optimizer.image_cache import ImageCache
from services.optimizer.planning import OptimizerContext, next_pose
from services.optimizer.proxies import ProxyKind
from simulation import SceneSimulator

START = GridIndex(lat=0, lon=3)


@pytest.fixture(scope="module")
def demo(catalog):
    scene = catalog.get("demo")
    grid = scene.spec.search.grid()
    simulator = SceneSimulator.from_scene(scene)
    views = simulator.grid_views(grid)

    def detections(flat: int) -> list[dict]:
        observation = simulator.clean_observation(views, flat)
        return [d.model_dump(mode="json") for d in simulator.detections(observation)]

    return grid, detections


def context(catalog, images: ImageCache | None = None) -> OptimizerContext:
    images = ImageCache() if images is None else images
    return OptimizerContext(calibrations=CalibrationStore.load(), catalog=catalog, images=images)


def body(demo, target: list[dict], history: list[int], **extra) -> str:
    grid, detections = demo
    views = [
        {
            "pose": grid.unflat(flat).model_dump(),
            "image_size": [320, 240],
            "detections": detections(flat),
        }
        for flat in history
    ]
    target_image = {"image_size": [320, 240], "detections": target}
    return json.dumps({"scene": "demo", "target": target_image, "history": views, **extra})


def search(demo, ctx: OptimizerContext, goal: GridIndex) -> list[NextPoseResponse]:
    """A simple search as the controller runs it: every request parsed from new JSON and
    carrying the whole history; checks the image cache's counts after each request."""
    grid, detections = demo
    target = detections(grid.flat(goal))
    history = [grid.flat(START)]
    answers: list[NextPoseResponse] = []
    cache = ctx.images
    for _ in range(40):
        hits, misses = cache.hits, cache.misses
        request = NextPoseRequest.model_validate_json(
            body(demo, target, history, strategy="simple")
        )
        answers.append(next_pose(request, ctx))
        new = 0 if history[-1] in history[:-1] else 1  # a pose visited again is found again
        if cache.max_bytes:
            first = len(history) == 1
            assert (cache.hits - hits, cache.misses - misses) == (
                len(history) - new + (0 if first else 1),
                new + (1 if first else 0),  # the target once per search
            )
        if answers[-1].done:
            return answers
        history.append(grid.flat(answers[-1].next.index))
    raise AssertionError("the search did not finish")


def test_a_search_processes_each_image_once_and_answers_as_without_the_cache(catalog, demo):
    cached = context(catalog)
    answers = search(demo, cached, GridIndex(lat=9, lon=30))
    assert len(answers) > 10
    assert len(cached.images) == cached.images.misses <= len(answers) + 1
    assert 0 < cached.images.nbytes <= cached.images.max_bytes
    uncached = context(catalog, ImageCache(max_bytes=0))
    assert search(demo, uncached, GridIndex(lat=9, lon=30)) == answers
    assert len(uncached.images) == uncached.images.hits == 0


def test_the_current_views_second_boxes_are_told_from_the_cache_too(catalog, demo):
    """A note on a merged second box belongs to the answer whose current view has it, cached
    or not; the same view earlier in the history is not told again."""
    grid, detections = demo
    ctx = context(catalog)
    doubled = grid.flat(GridIndex(lat=4, lon=7))
    first = detections(doubled)[0]
    second = {**first, "label": "cube" if first["label"] != "cube" else "sphere"}
    target = detections(grid.flat(GridIndex(lat=8, lon=3)))
    views = [grid.flat(START), doubled]

    def answer(history: list[int]) -> NextPoseResponse:
        raw = json.loads(body(demo, target, history))
        for view in raw["history"]:
            if view["pose"] == grid.unflat(doubled).model_dump():
                view["detections"].append({**second, "confidence": first["confidence"] / 2})
        return next_pose(NextPoseRequest.model_validate(raw), ctx)

    told = answer(views)
    assert "current view: " in told.reason
    assert answer(views) == told  # every image from the cache now
    assert ctx.images.hits == 3
    later = answer([*views, grid.flat(GridIndex(lat=5, lon=7))])
    assert "current view: " not in later.reason


def test_images_failing_a_check_are_refused_every_time_and_not_kept(catalog, demo):
    grid, detections = demo
    ctx = context(catalog)
    target = detections(grid.flat(GridIndex(lat=8, lon=3)))
    raw = json.loads(body(demo, target, [grid.flat(START)]))
    next_pose(NextPoseRequest.model_validate(raw), ctx)
    kept = len(ctx.images)
    # The same view on another camera: its image no longer has the camera's aspect ratio.
    square = {"fov_deg": 45, "width": 320, "height": 320, "radius": 8.0}
    grid_spec = {"angle_step_deg": 7.5, "min_theta_deg": 7.5, "max_theta_deg": 82.5}
    other = {**raw, "camera": square, "grid": grid_spec}
    del other["scene"]
    other["target"] = {**raw["target"], "image_size": [320, 320]}
    outside = {
        **raw,
        "history": [*raw["history"], {**raw["history"][0], "pose": {"lat": 99, "lon": 0}}],
    }
    for bad, field in ((other, "history[0].image_size"), (outside, "history[1].pose.lat")):
        for _ in range(2):
            with pytest.raises(UnprocessableError) as refused:
                next_pose(NextPoseRequest.model_validate(bad), ctx)
            assert refused.value.field == field
    assert len(ctx.images) == kept + 1  # only the square target, which passed its checks


def test_the_setting_tells_cameras_grids_and_classes_apart(demo):
    grid, _ = demo
    camera = CameraSpec(fov_deg=45.0, width=320, height=240, radius=8.0)
    settings = {
        ImageCache.setting(camera, grid, None),
        ImageCache.setting(camera.model_copy(update={"radius": 8.5}), grid, None),
        ImageCache.setting(camera, grid_for(15.0, 15.0, 75.0), None),
        ImageCache.setting(camera, grid, {"ball": ProxyKind.SPHERE}),
        ImageCache.setting(camera, grid, {"ball": ProxyKind.PRISM}),
    }
    assert len(settings) == 5
    assert ImageCache.setting(camera, grid, {"a": ProxyKind.CONE, "b": ProxyKind.SPHERE}) == (
        ImageCache.setting(camera, grid, {"b": ProxyKind.SPHERE, "a": ProxyKind.CONE})
    )


def test_the_cache_is_bounded_by_bytes_and_shares_read_only_arrays(catalog, demo):
    grid, detections = demo
    probe = context(catalog)
    target = detections(grid.flat(GridIndex(lat=8, lon=3)))
    next_pose(NextPoseRequest.model_validate_json(body(demo, target, [0])), probe)
    per_image = probe.images.nbytes / len(probe.images)
    ctx = context(catalog, ImageCache(max_bytes=int(4.5 * per_image)))
    request = NextPoseRequest.model_validate_json(body(demo, target, list(range(0, 60, 6))))
    answer = next_pose(request, ctx)
    assert len(ctx.images) == 4
    assert ctx.images.nbytes <= ctx.images.max_bytes
    assert next_pose(request, ctx) == answer
    assert ctx.images.hits == 0  # 11 images in turn through room for 4: the oldest goes first
    setting = ImageCache.setting(catalog.get("demo").spec.camera, grid, None)
    seen = ctx.images.get(setting, request.history[-1], lambda: pytest.fail("not kept"))
    with pytest.raises(ValueError, match="read-only"):
        seen.observation.boxes[0, 0] = 0.0  # shared by every request bringing the view
    ctx.images.clear()
    assert (len(ctx.images), ctx.images.hits, ctx.images.misses, ctx.images.nbytes) == (0, 0, 0, 0)


def test_a_view_equal_in_content_is_one_entry_whatever_object_carries_it(catalog, demo):
    grid, detections = demo
    ctx = context(catalog)
    target = detections(grid.flat(GridIndex(lat=8, lon=3)))
    text = body(demo, target, [5, 6])
    one = NextPoseRequest.model_validate_json(text)
    two = NextPoseRequest.model_validate(json.loads(text))
    assert one.history[0] is not two.history[0]
    assert next_pose(one, ctx) == next_pose(two, ctx)
    assert (ctx.images.hits, ctx.images.misses) == (3, 3)
    moved = json.loads(text)
    moved["history"][0]["detections"][0]["box"][0] += 0.5
    next_pose(NextPoseRequest.model_validate(moved), ctx)
    assert (ctx.images.hits, ctx.images.misses) == (5, 4)


def test_the_key_holds_every_field_of_an_image():
    """The key names the fields of an image, a detection and a pose it holds; a field added to
    these messages must be added to the key (or an image differing only there would be found)."""
    assert (
        set(ImageDetections.model_fields)
        == set(TargetImage.model_fields)
        == {
            "image_size",
            "detections",
        }
    )
    assert set(VisitedView.model_fields) == {"image_size", "detections", "pose"}
