"""The random-scene bench: photo and changed targets, failure traces, the θ-band table, and a
CI-sized run through the real stack (general model only: no torch needed)."""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime

import cv2
import numpy as np
import pytest

from cosmos.bench.altered import INTENSITY_RANGE, MOVE_RANGE, alter_scene
from cosmos.bench.random_report import (
    BANDS,
    band_cells,
    band_table,
    goal_checks,
    theta_band,
)
from cosmos.bench.results_md import section_of_random
from cosmos.bench.runner import SearchRecord
from cosmos.bench.scenes import generate_scene
from cosmos.bench.traces import failure_trace
from cosmos.bench.variants import degrade, photo_finish
from cosmos.cli import main
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.contracts.search import Search
from services.common.geometry.pose import GridIndex
from services.common.geometry.scene import load_scene

# -- photo and changed ----------------------------------------------------------------------


def _without_assets(data):
    """A scene document with asset paths reduced to their file names (copies move them)."""
    out = json.loads(json.dumps(data))
    for part in (out["ground"], *out["objects"]):
        for key in ("texture", "file"):
            if key in part:
                part[key] = part[key].rsplit("/", 1)[-1]
    return out


@pytest.fixture(params=["garden", "random"])
def scene(request, tmp_path):
    if request.param == "garden":
        return load_scene(BUILTIN_SCENES_DIR / "garden.yaml")
    return load_scene(generate_scene(4, tmp_path / "src", "r4"))


def test_photo_moves_and_scales_the_light_only(scene, tmp_path):
    for seed in range(8):
        copy = alter_scene(scene, "photo", np.random.default_rng(seed), tmp_path, f"p{seed}")
        altered = load_scene(tmp_path / f"{copy.id}.yaml")  # valid, assets resolved
        before, after = scene.spec.lighting.point, altered.spec.lighting.point
        assert math.dist(before.position, after.position) > 1.0
        assert 5.0 <= math.degrees(math.acos(after.position[2] / math.hypot(*after.position)))
        ratio = after.intensity / before.intensity
        assert INTENSITY_RANGE[0] - 1e-3 <= ratio <= INTENSITY_RANGE[1] + 1e-3
        assert "intensity ×" in copy.change
        a = _without_assets(scene.spec.model_dump(mode="json", exclude_none=True))
        b = _without_assets(altered.spec.model_dump(mode="json", exclude_none=True))
        a["lighting"]["point"] = b["lighting"]["point"] = None
        assert a == b


def test_changed_moves_one_object_on_the_ground_or_leaves_it_out(scene, tmp_path):
    moved = left_out = 0
    for seed in range(16):
        copy = alter_scene(scene, "changed", np.random.default_rng(seed), tmp_path, f"c{seed}")
        altered = load_scene(tmp_path / f"{copy.id}.yaml")
        assert altered.spec.camera == scene.spec.camera
        assert altered.spec.search == scene.spec.search
        before = {o.name: o for o in scene.spec.objects}
        after = {o.name: o for o in altered.spec.objects}
        if len(after) < len(before):
            left_out += 1
            assert len(before) - len(after) == 1
            assert "left out" in copy.change
            continue
        moved += 1
        changed = [n for n in before if before[n].position != after[n].position]
        assert len(changed) == 1
        (name,) = changed
        distance = math.dist(before[name].position, after[name].position)
        assert MOVE_RANGE[0] - 1e-3 <= distance <= MOVE_RANGE[1] + 1e-3
        half = altered.spec.ground.size / 2
        assert max(abs(v) for v in after[name].position) <= half
        assert name in copy.change
    assert moved
    assert left_out


def _image(seed=0):
    rng = np.random.default_rng(seed)
    image = np.full((60, 80, 3), 90, np.uint8)
    image[::4] = 200  # stripes: something for the blur to soften
    image[20:40, 20:50] = rng.integers(30, 230, size=3)
    return image


def test_photo_finish_changes_exposure_gamma_and_sharpness_reproducibly():
    image = _image()
    a = photo_finish(image, np.random.default_rng(3))
    assert a.shape == image.shape
    assert a.dtype == np.uint8
    assert np.array_equal(a, photo_finish(image, np.random.default_rng(3)))
    assert not np.array_equal(a, image)

    def sharpness(x):
        return float(cv2.Laplacian(x.astype(np.float64), cv2.CV_64F).var())

    assert sharpness(a) < 0.8 * sharpness(image)
    ok, png = cv2.imencode(".png", image)
    assert ok
    assert degrade(bytes(png), "changed", np.random.default_rng(0)) == bytes(png)
    photo = cv2.imdecode(
        np.frombuffer(degrade(bytes(png), "photo", np.random.default_rng(3)), np.uint8),
        cv2.IMREAD_COLOR,
    )
    assert np.array_equal(photo, a)


# -- traces ---------------------------------------------------------------------------------


def _det(label, x=10.0):
    return {"label": label, "class_id": 0, "confidence": 0.9, "box": [x, 10.0, x + 20, 30.0]}


def _iteration(index, lat, lon, detections, reason):
    return {
        "index": index,
        "pose": {"index": {"lat": lat, "lon": lon}, "theta_deg": 10.0 * lat, "phi_deg": 0.0},
        "image_size": [320, 240],
        "detections": detections,
        "timings": {"render_ms": 1.0, "detect_ms": 1.0, "optimize_ms": 1.0, "total_ms": 3.0},
        "reason": reason,
    }


def _search(status="failed", result=None, error=None):
    now = datetime.now(UTC).isoformat()
    return {
        "id": "s1",
        "status": status,
        "scene": "demo",
        "strategy": "reprojection",
        "start": {"index": {"lat": 0, "lon": 0}, "theta_deg": 0.0, "phi_deg": 0.0},
        "seed": 1,
        "max_iterations": 60,
        "created_at": now,
        "updated_at": now,
        "target_size": [320, 240],
        "target_detections": [_det("cube"), _det("sphere", 40), _det("mesh", 70)],
        "iterations": [
            _iteration(0, 0, 0, [_det("cube")], "moving towards the estimate"),
            {
                **_iteration(1, 3, 2, [_det("cube"), _det("sphere", 40)], "no match: RMS 4.1 px"),
                "match": {
                    "rms_px": 4.1,
                    "noise_px": 1.5,
                    "pairs": 2,
                    "unpaired_current": 0.0,
                    "unpaired_target": 0.9,
                    "score": 0.31,
                },
            },
            _iteration(2, 4, 1, [_det("cube")], "stuck: going round in circles"),
        ],
        "result": result,
        "error": error,
    }


def test_a_trace_says_where_the_truth_was_visited_and_why_it_was_rejected():
    raw = _search(error={"type": "about:blank", "title": "Search failed", "status": 422,
                         "detail": "gave up after 3 views"})  # fmt: skip
    Search.model_validate(raw)  # what the controller answers, as recorded
    trace = failure_trace(raw, GridIndex(lat=3, lon=2))
    assert trace.truth_visited
    assert trace.visit_iteration == 2
    assert trace.visit_reason == "no match: RMS 4.1 px"
    assert trace.visit_match["score"] == 0.31
    assert (trace.visit_detections, trace.target_detections) == (2, 3)
    assert trace.visit_labels == ("cube", "sphere")
    assert trace.target_labels == ("cube", "mesh", "sphere")
    assert trace.status == "failed"
    assert trace.final_reason == "gave up after 3 views"
    assert trace.iterations == 3
    assert trace.found is None
    assert trace.confirmed is None
    never = failure_trace(raw, GridIndex(lat=7, lon=7))
    assert not never.truth_visited
    assert never.visit_iteration is None


def test_a_trace_reads_an_unconfirmed_answer():
    result = {
        "pose": {"index": {"lat": 4, "lon": 1}, "theta_deg": 40.0, "phi_deg": 0.0},
        "refined_pose": {"theta_deg": 40.0, "phi_deg": 0.0},
        "confidence": 0.4,
        "renders": 3,
        "reason": "best visited view",
        "confirmed": False,  # newer than this tree's SearchResult: read from the JSON
    }
    trace = failure_trace(_search("succeeded", result), GridIndex(lat=4, lon=1))
    assert trace.truth_visited
    assert trace.visit_iteration == 3
    assert trace.found == GridIndex(lat=4, lon=1)
    assert trace.confirmed is False
    assert trace.final_reason == "best visited view"


# -- the θ-band table -----------------------------------------------------------------------


def _record(
    theta, variant="clean", arm="general", found=True, confirmed=True, renders=2, wrong=False
):
    truth = GridIndex(lat=3, lon=0)
    return SearchRecord(
        scene="r",
        strategy="reprojection",
        variant=variant,
        number=0,
        search_id="x",
        status="succeeded" if found or wrong else "failed",
        true_theta_deg=theta,
        true_phi_deg=0.0,
        truth=truth,
        start=GridIndex(lat=0, lon=0),
        found=truth if found else (GridIndex(lat=4, lon=0) if wrong else None),
        success=found,
        renders=renders,
        iterations=renders,
        arm=arm,
        confirmed=confirmed if found or wrong else None,
    )


def test_theta_bands():
    assert [theta_band(t) for t in (0, 29.9, 30, 60, 60.1, 90)] == [
        BANDS[0], BANDS[0], BANDS[1], BANDS[1], BANDS[2], BANDS[2]
    ]  # fmt: skip


def test_the_band_table_counts_per_arm_variant_and_band():
    records = [
        _record(10),
        _record(45),
        _record(75, found=False, renders=9, wrong=True),
        _record(75, variant="photo", confirmed=False),
        _record(10, arm="scene"),
        _record(45, arm="scene"),
        _record(75, arm="scene"),
        _record(75, variant="photo", arm="scene"),
    ]
    cells = {(c.arm, c.variant, c.band): c for c in band_cells(records)}
    general = cells[("general", "all", "all")]
    assert (general.n, general.found, general.confirmed) == (4, 3, 2)
    assert (general.unconfirmed, general.unconfirmed_found) == (1, 1)
    assert general.confirmed_wrong == 1
    assert cells[("scene", "all", "all")].confirmed_wrong == 0
    high = cells[("general", "all", BANDS[2])]
    assert (high.n, high.found) == (2, 1)
    assert cells[("general", "clean", BANDS[2])].found_rate == 0.0
    assert ("general", "photo", BANDS[0]) not in cells
    assert cells[("scene", "all", "all")].found_rate == 1.0
    text = band_table(list(cells.values()), markdown=True)
    assert "| general | clean | 1/1 = 100.0% | 1/1 = 100.0% | 0/1 = 0.0% | 2/3 = 66.7% |" in text
    goals = goal_checks(list(cells.values()))
    assert "general: overall 75.0% (goal ≥ 99%): MISSED" in goals
    assert "scene: overall 100.0% (goal ≥ 99%): met" in goals
    assert "scene: every band and variant at goal: met" in goals
    assert any(line.startswith("general: every band") and "clean/all" in line for line in goals)


def test_the_random_section_lists_scenes_models_table_goals_and_traces():
    record = _record(75, found=False)
    trace = failure_trace(_search(), GridIndex(lat=3, lon=2))
    record = record.model_copy(update={"trace": trace})
    data = {
        "command": "cosmos bench --random-scenes 1",
        "machine": {"cpu": "test"},
        "duration_s": 12.0,
        "notes": ["onboarding skipped (--onboard none)"],
        "scenes": [
            {
                "id": "r",
                "film": "320x240",
                "fov_deg": 40.0,
                "radius": 8.0,
                "angle_step_deg": 7.5,
                "objects": 2,
                "kinds": ["star", "cube"],
                "ground": "texture",
            }
        ],  # fmt: skip
        "models": [{"scene": "r", "arm": "general", "served": "general: detector"}],
        "records": [_record(10).model_dump(mode="json"), record.model_dump(mode="json")],
    }
    text = section_of_random(data)
    assert "## Random scenes" in text
    assert "| r | 320x240 | 40.0 | 8.00 | 7.5 | star, cube |" in text
    assert "**Goals**" in text
    assert (
        "yes, at 2 (match score 0.31: RMS 4.10 px, noise 1.50 px, 2 pairs): no match: RMS 4.1 px"
        in text
    )
    assert "onboarding skipped" in text


# -- end to end -----------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_ci_sized_random_scene_bench_through_the_real_stack(tmp_path, capsys):
    out = tmp_path / "results"
    status = main(
        [
            "bench",
            "--random-scenes", "1",
            "--n", "1",
            "--onboard", "none",
            "--variants", "clean,photo,changed",
            "--starts", "predicted",
            "--max-iterations", "20",
            "--seed", "3",
            "--scenes-out", str(tmp_path / "scenes"),
            "--out", str(out),
            "--results-md", str(tmp_path / "RESULTS.md"),
        ]
    )  # fmt: skip
    printed = capsys.readouterr().out
    assert status == 0, printed
    report = json.loads((out / "random.json").read_text())
    records = [SearchRecord.model_validate(r) for r in report["records"]]
    assert [r.variant for r in records] == ["clean", "photo", "changed"]
    assert all(r.arm == "general" and r.status != "error" for r in records)
    assert not any(r.start_given for r in records)  # searched without a start
    assert "general, predicted start" in printed
    assert all((r.trace is None) == (r.success and r.confirmed is not False) for r in records)
    assert records[1].change.startswith("light turned")
    assert records[2].change
    assert report["models"] == [
        {"scene": "rand3-0", "arm": "general", "served": report["models"][0]["served"]}
    ]
    assert report["models"][0]["served"].startswith("general")
    assert (tmp_path / "scenes" / "scenes" / "rand3-0.yaml").exists()
    results = (tmp_path / "RESULTS.md").read_text()
    assert "## Random scenes" in results
    assert "| arm | variant | θ < 30° |" in results


# -- onboarding, without torch --------------------------------------------------------------


def test_without_training_only_the_general_arm_runs(monkeypatch):
    from cosmos.bench import random_run

    def missing(name):
        raise ModuleNotFoundError(f"No module named {name!r}")

    monkeypatch.setattr(random_run.importlib, "import_module", missing)
    onboard, why = random_run.onboarder("tiny")
    assert onboard is None
    assert "onboarding unavailable" in why


def test_the_onboard_preset_reaches_onboard_scene(monkeypatch, tmp_path):
    from types import SimpleNamespace

    from cosmos.bench import random_run

    calls = []

    class Options:
        def __init__(self, name="default"):
            self.name = name

        @classmethod
        def tiny(cls):
            return cls("tiny")

    def onboard_scene(path, options, *, work_dir=None, progress=None):
        calls.append((path, options.name, work_dir))
        return SimpleNamespace(minutes=0.5, precision=0.9, recall=0.8, map50=0.85)

    fake = SimpleNamespace(OnboardOptions=Options, onboard_scene=onboard_scene)
    monkeypatch.setattr(random_run.importlib, "import_module", lambda name: fake)
    for preset in ("tiny", "default"):
        onboard, why = random_run.onboarder(preset)
        assert why == ""
        report = onboard(tmp_path / "s.yaml", tmp_path / "work")
        assert random_run.onboarding_summary(report) == "0.5 min, P 0.900, R 0.800, mAP50 0.850"
    assert [c[1] for c in calls] == ["tiny", "default"]
    assert calls[0][2] == tmp_path / "work"


def test_the_scene_arm_searches_only_scenes_whose_own_model_serves(monkeypatch, tmp_path):
    from cosmos.bench import random_run
    from cosmos.bench.runner import BenchTarget
    from cosmos.bench.session import BenchConfig, Endpoints
    from services.common.geometry.pose import Pose

    pose = Pose(theta_deg=30.0, phi_deg=0.0)
    index = GridIndex(lat=1, lon=0)
    targets = [
        BenchTarget(
            s, b"png", index, pose, start=index, start_pose=pose, seed=1, variant="clean", number=0
        )
        for s in ("a", "b", "c")
    ]

    def onboard(path, work_dir):
        if path.stem == "c":
            raise RuntimeError("training diverged")
        return None

    monkeypatch.setattr(random_run, "MODEL_WAIT_S", 0.0)
    monkeypatch.setattr(
        random_run,
        "served_model",
        lambda url, scene, image, token=None: {
            "name": "m",
            "sha256": "0" * 64,
            "scene": scene * (scene == "a"),
        },
    )
    searched = []

    def run_searches(url, jobs, **kw):
        searched.append(([t.scene for t, _ in jobs], kw["arm"]))
        return [_record(30.0, arm=kw["arm"]) for _ in jobs]

    monkeypatch.setattr(random_run, "run_searches", run_searches)
    monkeypatch.setattr(
        random_run, "model_status", lambda url, scene, token: "refused: wrong classes"
    )
    models: list = []
    config = BenchConfig(
        scenes=("a", "b", "c"), strategies=("reprojection",), starts=("given",), onboard="tiny"
    )
    endpoints = Endpoints("http://c", "http://r", detectors=("http://d",))
    records = random_run._scene_arm(
        config, endpoints, targets, tmp_path, tmp_path / "work", onboard, models
    )
    assert searched == [(["a"], "scene"), (["a"], "scene")]  # the untimed warm-up, then the run
    assert [r.arm for r in records] == ["scene"]
    by_scene = {m["scene"]: m for m in models}
    assert by_scene["a"]["served"].startswith("the scene's own (a)")
    assert by_scene["b"]["served"].startswith("general")
    assert by_scene["b"]["served"].endswith("the scene's own model: refused: wrong classes")
    assert by_scene["c"]["onboarding"] == "failed: RuntimeError: training diverged"


def test_model_status_reads_get_models(monkeypatch):
    import httpx

    from cosmos.bench import random_run

    body = {
        "general": {},
        "scenes": [
            {"scene": "a", "state": "serving", "classes": 3},
            {"scene": "b", "state": "refused", "error": "sha256 mismatch", "classes": 2},
        ],
    }

    def get(url, timeout, headers):
        assert url == "http://d/models"
        assert headers == {"Authorization": "Bearer tttttttttttttttt"}
        return httpx.Response(200, json=body, request=httpx.Request("GET", url))

    monkeypatch.setattr(random_run.httpx, "get", get)
    token = "t" * 16
    assert random_run.model_status("http://d", "a", token) == "serving"
    assert random_run.model_status("http://d", "b", token) == "refused: sha256 mismatch"
    assert random_run.model_status("http://d", "c", token) == "not listed by GET /models"


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_the_scene_arm_runs_with_a_model_the_detector_picks_up_without_restart(
    tmp_path, monkeypatch, capsys
):
    """Onboarding stood in for by a model that finds one object of the scene's first class
    everywhere, installed as onboarding installs one: the running detector must serve it, and
    the same targets run again labelled ``scene``."""
    from cosmos.bench import random_run
    from tests.scene_model_support import stand_in_onboarding

    monkeypatch.setattr(random_run, "onboarder", lambda preset: (stand_in_onboarding, ""))
    out = tmp_path / "results"
    status = main(
        [
            "bench",
            "--random-scenes", "1",
            "--n", "1",
            "--onboard", "tiny",
            "--variants", "clean",
            "--starts", "given",
            "--max-iterations", "8",
            "--seed", "3",
            "--out", str(out),
            "--results-md", "",
        ]
    )  # fmt: skip
    printed = capsys.readouterr().out
    assert status == 0, printed
    report = json.loads((out / "random.json").read_text())
    assert [r["arm"] for r in report["records"]] == ["general", "scene"]
    served = {m["arm"]: m["served"] for m in report["models"]}
    assert served["general"].startswith("general")
    assert served["scene"].startswith("the scene's own (rand3-0)")
