"""``cosmos bench --free``: free targets searched through the real stack (issue 23, item 5). A
short run on the demo scene checks the report's structure and that its figures come from the
answers; the checkpoint and the confirmed-wrong count are checked on their own."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks import free_truth
from benchmarks.free_replay import replayed
from benchmarks.free_truth import right_and_stray
from cosmos.bench import free_run
from cosmos.bench.free_bench import searching
from cosmos.bench.free_bench.checkpoint import Checkpoint
from cosmos.bench.free_bench.records import (
    ANSWER,
    BASELINE,
    BOUND,
    BOXES,
    METHODS,
    CameraRecord,
    FreeRecord,
)
from cosmos.bench.free_bench.report import (
    confirmed_wrong,
    free_tables,
    goal_checks,
    within,
    wrong_line,
)
from cosmos.bench.free_targets.draw import BANDS
from cosmos.bench.free_targets.metrics import THRESHOLDS
from cosmos.cli import main
from services.common.catalog import SceneCatalog
from services.common.geometry.free_camera import FreeCamera
from services.optimizer.free_pose import SceneObjectCache
from services.renderer.settings import RendererSettings

DEMO_RADIUS = 8.0

# -- records, the confirmed-wrong count and the checkpoint, without a stack ----------------


def camera(position, yaw_deg=0.0, fov_deg=45.0) -> CameraRecord:
    x, y, z, w = Rotation.from_euler("z", yaw_deg, degrees=True).as_quat()
    return CameraRecord(position=position, quaternion_wxyz=(w, x, y, z), fov_deg=fov_deg)


def record(index=0, outcome="found", answer=None, **fields) -> FreeRecord:
    truth = camera((0.0, 0.0, 5.0))
    values = {
        "scene": "demo",
        "random": False,
        "variant": "clean",
        "index": index,
        "band": "nadir",
        "elevation_deg": 90.0,
        "intrinsics_given": True,
        "objects": 4,
        "radius": DEMO_RADIUS,
        "truth": truth,
        "status": "succeeded",
        "outcome": outcome,
        "renders": 1,
        "wall_ms": 500.0,
        "poses": {ANSWER: answer or truth, BOXES: truth, BASELINE: None, BOUND: truth},
    }
    return FreeRecord.model_validate(values | fields)


def test_errors_come_from_the_poses():
    moved = record(answer=camera((0.8, 0.0, 5.0), yaw_deg=3.0, fov_deg=45.9))
    error = moved.error(ANSWER)
    assert error.position == pytest.approx(0.8 / DEMO_RADIUS)
    assert error.rotation_deg == pytest.approx(3.0)
    assert error.fov_pct == pytest.approx(2.0)
    assert moved.error(BOXES).position == 0.0
    assert math.isinf(moved.error(BASELINE).position)  # no pose: a miss


def test_a_found_answer_outside_five_percent_and_two_degrees_is_confirmed_wrong():
    far = camera((0.5, 0.0, 5.0))  # 6.25 % of the radius
    records = [
        record(0),
        record(1, answer=far),
        record(2, outcome="ambiguous", answer=far),  # not vouched for: not confirmed wrong
        record(3, answer=camera((0.0, 0.0, 5.0), yaw_deg=2.5)),
    ]
    assert [r.index for r in confirmed_wrong(records)] == [1, 3]
    assert wrong_line(records).startswith("Confirmed wrong: 2 of 3 found answers")
    assert within(records, ANSWER, THRESHOLDS[1]) == 0.25
    assert any(
        line.startswith("MISSED: fov given: answer 25% within 5 %/2°")
        for line in goal_checks(records)
    )


def last_table_rows(records: list[FreeRecord]) -> dict[str, list[str]]:
    """The last of the tables' clean rows, by their second column, as markdown cells."""
    return {
        cells[1].strip(): cells
        for line in free_tables(records, markdown=True).split("\n\n")[-1].splitlines()
        if (cells := line.split("|")[1:-1])[0].strip() == "clean"
    }


def test_lenses_beyond_thirty_percent_get_their_own_table():
    far = camera((0.5, 0.0, 5.0))
    issue = [record(0, fov_factor=0.95), record(1, fov_factor=1.3), record(2)]
    assert [r.lens for r in issue] == ["±30 %", "±30 %", "unknown"]  # the last: an older report
    assert "lens" not in free_tables(issue)
    drone = [*issue, record(3, fov_factor=1.31, answer=far), record(4, fov_factor=0.69)]
    assert [r.lens for r in drone[3:]] == ["wider", "narrower"]
    rows = last_table_rows(drone)
    assert list(rows) == ["narrower", "±30 %", "wider", "unknown", "all"]
    assert rows["wider"][2].strip() == "1"
    assert rows["wider"][3].strip().startswith("0% · 0%")  # the one wider lens, 6.25 % off
    assert rows["±30 %"][3].strip().startswith("100% · 100%")


def test_rolls_beyond_twenty_five_degrees_get_their_own_table():
    far = camera((0.5, 0.0, 5.0))
    issue = [record(0, roll_deg=-25.0), record(1, roll_deg=3.0), record(2)]
    assert [r.roll for r in issue] == ["±25°", "±25°", "unknown"]  # the last: an older report
    assert "roll" not in free_tables(issue)
    upright = [*issue, record(3, roll_deg=-88.0, answer=far), record(4, roll_deg=40.0)]
    assert [r.roll for r in upright[3:]] == ["60-90°", "25-60°"]
    edges = [record(5 + i, roll_deg=d) for i, d in enumerate((25.01, 60.0, 90.0, -90.5))]
    assert [r.roll for r in edges] == ["25-60°", "25-60°", "60-90°", "beyond 90°"]
    rows = last_table_rows(upright)
    assert list(rows) == ["±25°", "25-60°", "60-90°", "unknown", "all"]
    assert rows["60-90°"][2].strip() == "1"
    assert rows["60-90°"][3].strip().startswith("0% · 0%")  # the one rolled 88°, 6.25 % off
    assert rows["25-60°"][3].strip().startswith("100% · 100%")


def test_the_checkpoint_resumes_and_sets_another_run_aside(tmp_path):
    path = tmp_path / "free.checkpoint.jsonl"
    first = Checkpoint(path, {"seed": 1})
    first.add(record(0))
    first.add(record(1))
    with path.open("a") as file:
        file.write('{"scene": "demo", "vari')  # a run killed mid-line
    again = Checkpoint(path, {"seed": 1})
    assert sorted(again.records) == [("demo", "clean", 0, False), ("demo", "clean", 1, False)]
    assert not again.set_aside
    other = Checkpoint(path, {"seed": 2})
    assert other.set_aside
    assert not other.records
    assert (tmp_path / "free.checkpoint.jsonl.old").exists()
    other.remove()
    assert not path.exists()


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        (["--target-width", "400"], "--target-width draws free targets: add --free"),
        (["--free", "--target-width", "4096"], "--target-width must be 16 to 2048 pixels"),
        (["--free", "--target-width", "0"], "--target-width must be 16 to 2048 pixels"),
        (["--fov-range", "1,2"], "--fov-range draws free targets: add --free"),
        (["--free", "--fov-range", "2,1"], "--fov-range wants 0 < LO <= HI < 10"),
        (["--free", "--fov-range", "0,1"], "--fov-range wants 0 < LO <= HI < 10"),
        (["--free", "--fov-range", "nan,1"], "--fov-range wants 0 < LO <= HI < 10"),
        (["--free", "--fov-range", "1"], "--fov-range wants LO,HI (two numbers)"),
        (["--target-aspect", "16:9"], "--target-aspect draws free targets: add --free"),
        (["--roll-limit", "90"], "--roll-limit draws free targets: add --free"),
        (["--free", "--roll-limit", "-1"], "--roll-limit wants 0 to 180 degrees"),
        (["--free", "--roll-limit", "nan"], "--roll-limit wants 0 to 180 degrees"),
        (["--free", "--target-aspect", "16x9"], "--target-aspect wants W:H (two whole numbers)"),
        (["--free", "--target-aspect", "5:1"], "--target-aspect wants W:H between 1:4 and 4:1"),
        (["--free", "--target-aspect", "0:1"], "--target-aspect wants W:H between 1:4 and 4:1"),
    ],
)
def test_a_target_width_or_fov_range_is_refused_before_anything_runs(tmp_path, capsys, flags, said):
    status = main(["bench", *flags, "--out", str(tmp_path), "--results-md", ""])
    assert status == 1
    assert said in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


# -- through the real stack ------------------------------------------------------------------


def angle_deg(a: CameraRecord, b: CameraRecord) -> float:
    qa = Rotation.from_quat([*a.quaternion_wxyz[1:], a.quaternion_wxyz[0]])
    qb = Rotation.from_quat([*b.quaternion_wxyz[1:], b.quaternion_wxyz[0]])
    return float(np.degrees((qa.inv() * qb).magnitude()))


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_cosmos_bench_free_through_the_real_stack(tmp_path, capsys, monkeypatch):
    # Spies that keep what the controller answered and which target each search was for.
    answered, drawn = {}, {}
    real_post, real_search = searching.post_and_follow, free_run.search_target

    async def post_spy(http, base_url, image, query):
        raw, wall_ms = await real_post(http, base_url, image, query)
        answered[raw["id"]] = (raw, query)
        return raw, wall_ms

    async def search_spy(http, calls, target, image, **options):
        record = await real_search(http, calls, target, image, **options)
        drawn[record.search_id] = target
        return record

    monkeypatch.setattr(searching, "post_and_follow", post_spy)
    monkeypatch.setattr(free_run, "search_target", search_spy)
    out = tmp_path / "results"
    results_md = tmp_path / "RESULTS.md"
    status = main(
        [
            "bench", "--free",
            "--scene", "demo",
            "--n", "2",
            "--variants", "clean",
            "--seed", "1",
            "--target-width", "400",
            "--target-aspect", "16:9",
            "--roll-limit", "40",
            "--fov-range", "1.1,1.2",
            "--out", str(out),
            "--results-md", str(results_md),
        ]
    )  # fmt: skip
    printed = capsys.readouterr().out
    assert status == 0, printed
    report = json.loads((out / "free.json").read_text())
    assert report["complete"]
    assert report["planned"] == 2
    assert report["config"]["target_width"] == report["machine"]["target_width"] == 400
    assert report["config"]["fov_range"] == [1.1, 1.2]
    assert report["config"]["target_aspect"] == [16, 9]
    assert report["machine"]["target_aspect"] == "16:9"
    assert report["config"]["roll_limit"] == 40.0
    assert report["machine"]["target_roll"] == "within ±40°"
    assert report["machine"]["target_fov"] == "1.1-1.2 times the scene camera's"
    assert not (out / "free.checkpoint.jsonl").exists()  # removed once complete
    records = [FreeRecord.model_validate(r) for r in report["records"]]
    catalog, objects = SceneCatalog(RendererSettings().scene_directories()), SceneObjectCache()
    assert sorted((r.scene, r.variant, r.index) for r in records) == [
        ("demo", "clean", 0),
        ("demo", "clean", 1),
    ]
    for r in records:
        assert r.band in BANDS
        assert set(r.poses) == set(METHODS)
        assert r.search_id
        assert r.outcome in ("found", "ambiguous")
        assert r.renders >= 1
        assert r.wall_ms > 0
        assert r.floor_ms is not None
        assert r.floor_ms > 0
        assert r.detections >= 3
        assert r.render_ms > 0  # the search's own render, from its iterations' timings
        assert r.refine_ms > 0  # and the dense fit by it
        raw, query = answered[r.search_id]
        target = drawn[r.search_id]
        assert target.camera.fov_deg is not None  # --fov-range: 1.1-1.2 times demo's 45°
        assert 1.1 <= target.camera.fov_deg / 45.0 <= 1.2
        assert abs(target.camera.roll_deg) <= 40.0
        assert r.roll_deg == pytest.approx(target.camera.roll_deg, abs=1e-3)
        assert r.fov_factor == pytest.approx(target.camera.fov_deg / 45.0, abs=1e-3)
        assert query["mode"] == "free"
        if r.intrinsics_given:  # the fov went to the controller only when the target gives it
            assert float(query["fov_deg"]) == pytest.approx(target.annotations.camera.fov_deg)
        else:
            assert "fov_deg" not in query
        # the error the tables use is the controller's answer's distance to the drawn camera
        pose = raw["result"]["free"]["pose"]
        error = r.error(ANSWER)
        assert error.position == pytest.approx(
            math.dist(pose["position"], target.camera.position) / DEMO_RADIUS, abs=1e-3
        )
        found = FreeCamera(position=(0.0, 0.0, 1.0), quaternion_wxyz=pose["quaternion_wxyz"])
        relative = Rotation.from_matrix(found.rotation().T @ target.camera.rotation())
        assert error.rotation_deg == pytest.approx(relative.magnitude() * 180 / math.pi, abs=0.01)
        answer = r.poses[ANSWER]
        assert answer is not None
        assert error.rotation_deg == pytest.approx(angle_deg(answer, r.truth), abs=1e-3)
        # demo targets show ≥ 3 objects: the answer is near the truth, not an arbitrary pose
        assert error.within(0.10, 5.0), (error, r.reason)
        assert r.intrinsics_source == ("given" if r.intrinsics_given else "estimated")
        # the record keeps the target's detections: solved again offline, they give the pose
        # the search rendered first (benchmarks.free_replay)
        assert [d.box for d in r.target_detections] == [
            pytest.approx(d["box"], abs=1e-3) for d in raw["target_detections"]
        ]
        # --target-width 400 on --target-aspect 16:9, not the demo camera's 4:3
        assert r.target_size == tuple(raw["target_size"]) == (400, 225)
        again, _ = replayed(r, catalog, objects)
        first = r.error(BOXES)
        assert again.position == pytest.approx(first.position, abs=1e-3)
        assert again.rotation_deg == pytest.approx(first.rotation_deg, abs=0.05)
        # against the truth (benchmarks.free_truth): the demo's own model names what it boxes
        right, stray = right_and_stray(r, target, catalog.get("demo"))
        assert right >= 3, r.target_detections
        assert right + stray <= r.detections
    loose = sum(r.error(ANSWER).within(*THRESHOLDS[1]) for r in records)
    share = f"{loose / len(records):.0%}"
    all_row = next(line for line in printed.splitlines() if line.startswith("all variants"))
    assert f" · {share} · " in all_row
    assert "Confirmed wrong: " in printed
    assert "median renders per search" in printed
    assert "× the floor" in printed
    assert "time (medians, ms): wall " in printed
    # drawn again from the run's config (its film 400 x 225), the targets' truth lines up
    assert free_truth.main([str(out / "free.json"), "--all-intrinsics"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    own = [row for row in rows if row[0] == "own"]
    assert {row[1] for row in own} <= {"3", "≥4"}
    assert sum(int(row[2]) for row in own) == len(records)
    md = results_md.read_text()
    assert "## Free cameras through the local stack (`--free`)" in md
    assert f"```sh\n{report['command']}\n```" in md  # the command that prints it
    assert "| variant | elevation | n |" in md
    assert "**Confirmed wrong: " in md


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_generated_scene_is_searched_again_once_onboarded(tmp_path, capsys, monkeypatch):
    """``--onboard``: onboarding stood in for by a model that finds one object of the scene's
    first class everywhere, installed as onboarding installs one. The generated scene's target
    is searched with the general model, then again with the scene's own once the running
    detector serves it; the tables and goals split by detector."""
    from tests.scene_model_support import stand_in_onboarding

    monkeypatch.setattr(free_run, "onboarder", lambda preset: (stand_in_onboarding, ""))
    out = tmp_path / "results"
    status = main(
        [
            "bench", "--free",
            "--scene", "demo",
            "--random-scenes", "1",
            "--n", "1",
            "--onboard", "tiny",
            "--variants", "clean",
            "--seed", "3",
            "--out", str(out),
            "--results-md", "",
        ]
    )  # fmt: skip
    printed = capsys.readouterr().out
    assert status == 0, printed
    report = json.loads((out / "free.json").read_text())
    records = [FreeRecord.model_validate(r) for r in report["records"]]
    keys = sorted((r.scene, r.onboarded, r.detector) for r in records)
    assert keys == [("demo", False, "own"), ("rand3-0", False, "general"), ("rand3-0", True, "own")]
    own = next(r for r in records if r.onboarded)
    general = next(r for r in records if r.scene == "rand3-0" and not r.onboarded)
    assert own.truth == general.truth  # the same target
    assert own.detections == 1  # the stand-in model's one box
    assert any(note.startswith("rand3-0 onboarded") for note in report["notes"])
    assert "rand3-0 (own)" in printed
    assert "general detector: " in printed
    assert "own detector: " in printed
