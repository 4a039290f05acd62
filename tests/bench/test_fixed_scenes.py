"""``cosmos bench``: its target variants, its figures, and a CI-sized bench through a real stack.

The slow test runs the command itself on a few seeded targets per scene against the four real
services on loopback, with a loose success threshold: a regression that breaks searching (or the
bench) fails CI; the full figures live in docs/RESULTS.md.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from cosmos.bench.runner import IterationRecord, SearchRecord
from cosmos.bench.settings_choice import choose_setting
from cosmos.bench.settings_sweep import _match
from cosmos.bench.stats import eq9_rows, percentile, summarize
from cosmos.bench.tables import markdown_tables, text_tables
from cosmos.bench.variants import (
    JPEG_QUALITY,
    NOISE_SIGMA,
    OFFGRID_FRACTION,
    degrade,
    draw_pose,
)
from cosmos.cli import main
from services.common.contracts.detect import Detection
from services.common.contracts.render import ObjectAnnotation
from services.common.geometry.grid import grid_for
from services.common.geometry.pose import GridIndex
from services.common.geometry.sphere import angular_distance_deg
from services.detector.letterbox import fit

MODEL = Path(__file__).resolve().parents[2] / "models" / "detector.onnx"
GRID = grid_for(7.5, 7.5, 82.5)


def _png(seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    image = np.zeros((48, 64, 3), np.uint8)
    image[10:30, 12:40] = rng.integers(40, 220, size=3)
    image += rng.integers(0, 30, size=image.shape, dtype=np.uint8)
    ok, buffer = cv2.imencode(".png", image)
    assert ok
    return bytes(buffer)


def _decode(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image.astype(np.float64)


def test_clean_and_offgrid_targets_are_the_renderers_image():
    png = _png()
    rng = np.random.default_rng(0)
    assert degrade(png, "clean", rng) is png
    assert degrade(png, "offgrid", rng) is png


def test_jpeg_targets_are_jpeg_of_the_same_size():
    png = _png()
    jpeg = degrade(png, "jpeg", np.random.default_rng(0))
    assert jpeg.startswith(b"\xff\xd8")
    assert _decode(jpeg).shape == _decode(png).shape
    assert JPEG_QUALITY == 60


def test_noise_targets_have_the_promised_sigma_and_are_seeded():
    png = _png()
    noisy = degrade(png, "noise", np.random.default_rng(1))
    assert noisy == degrade(png, "noise", np.random.default_rng(1))
    diff = _decode(noisy) - _decode(png)
    assert abs(diff.mean()) < 0.5
    assert diff.std() == pytest.approx(NOISE_SIGMA, rel=0.1)  # clipping at 0/255 shaves a little


def test_on_grid_poses_are_grid_poses():
    rng = np.random.default_rng(3)
    for _ in range(50):
        target = draw_pose(GRID, "clean", rng)
        assert target.on_grid
        assert GRID.pose(target.truth) == target.pose


def test_offgrid_poses_stay_within_a_third_of_a_step_and_truth_is_the_nearest():
    rng = np.random.default_rng(4)
    step = GRID.angle_step_deg
    moved = 0
    for _ in range(300):
        target = draw_pose(GRID, "offgrid", rng)
        assert not target.on_grid
        assert target.truth == GRID.nearest(target.pose)
        nearest = GRID.pose(target.truth)
        distance = float(angular_distance_deg(target.pose, nearest))
        # a third of a step in θ and of the ring spacing in φ (≈ a step along the ring, a little
        # more on the first ring) from the drawn grid pose, and the nearest is no farther
        assert distance <= 1.5 * OFFGRID_FRACTION * step
        moved += distance > 1e-6
    assert moved > 290


def _record(strategy: str, renders: int, success: bool = True, wall: float = 500.0, **kw):
    trajectory = tuple(
        IterationRecord(
            lat=i,
            lon=0,
            theta_deg=7.5 * (i + 1),
            phi_deg=0.0,
            distance_deg=float(renders - 1 - i),
            render_ms=100.0,
            detect_ms=20.0,
            optimize_ms=10.0,
            total_ms=135.0,
        )
        for i in range(renders)
    )
    return SearchRecord(
        scene=kw.get("scene", "demo"),
        strategy=strategy,
        variant=kw.get("variant", "clean"),
        number=kw.get("number", 0),
        search_id="x",
        status="succeeded" if success else "failed",
        true_theta_deg=45.0,
        true_phi_deg=0.0,
        truth=GridIndex(lat=5, lon=0),
        start=GridIndex(lat=0, lon=0),
        found=GridIndex(lat=5, lon=0) if success else None,
        success=success,
        renders=renders,
        iterations=renders,
        wall_ms=wall,
        render_ms=100.0 * renders,
        detect_ms=20.0 * renders,
        optimize_ms=10.0 * renders,
        loop_ms=135.0 * renders,
        trajectory=trajectory,
    )


def test_percentiles_are_sample_values():
    assert percentile([1, 2, 3, 4], 50) == 2
    assert percentile([2, 2, 2, 3], 95) == 3
    assert math.isnan(percentile([], 50))


def test_summaries_and_eq9():
    records = [_record("simple", r, number=i) for i, r in enumerate([5, 11, 37])] + [
        _record("reprojection", 2, number=0),
        _record("reprojection", 2, number=1),
        _record("reprojection", 3, number=2, success=False),
    ]
    summaries = {s.strategy: s for s in summarize(records)}
    simple, ours = summaries["simple"], summaries["reprojection"]
    assert simple.n == 3
    assert simple.success_rate == 1.0
    assert simple.moves_mean == pytest.approx((4 + 10 + 36) / 3)
    assert simple.moves_max == 36
    assert ours.success_rate == pytest.approx(2 / 3)
    assert ours.renders_p50 == 2
    assert ours.renders_max == 3
    assert ours.other_ms == pytest.approx(500 - 130 * 7 / 3)
    (row,) = eq9_rows(list(summaries.values()))
    assert row.strategy == "reprojection"
    assert row.worst_change == pytest.approx((2 - 36) / 36)  # the paper's figure, by construction
    assert row.mean_change == pytest.approx((4 / 3 - 50 / 3) / (50 / 3))
    text = text_tables(list(summaries.values()))
    assert "-94.44%" in text
    assert "| demo | reprojection | 3 | 66.7% |" in markdown_tables(list(summaries.values()))


def test_unconfirmed_answers_are_counted_apart_in_the_summaries():
    records = [
        _record("reprojection", 2, number=0),
        _record("reprojection", 3, number=1).model_copy(update={"confirmed": False}),
    ]
    (summary,) = summarize(records)
    assert summary.success_rate == 1.0
    assert summary.unconfirmed_succeeded == 1
    assert "| demo | reprojection | 2 | 100.0% (1 unconfirmed) |" in markdown_tables([summary])


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_ci_sized_bench_through_the_real_stack(tmp_path, capsys):
    """A few seeded targets per scene and variant, every strategy for clean targets, the
    profile on two; loose thresholds (the full bench's figures are in docs/RESULTS.md)."""
    if not MODEL.exists() and "COSMOS_DETECTOR_MODEL" not in os.environ:
        pytest.fail(f"the shipped detector model {MODEL} is missing")
    out = tmp_path / "results"
    status = main(
        [
            "bench",
            "--n",
            "3",
            "--strategies",
            "reprojection",
            "--seed",
            "11",
            "--profile",
            "--profile-n",
            "1",
            "--out",
            str(out),
            "--results-md",
            str(tmp_path / "RESULTS.md"),
        ]
    )
    printed = capsys.readouterr().out
    assert status == 0, printed
    report = json.loads((out / "bench.json").read_text())
    records = [SearchRecord.model_validate(r) for r in report["records"]]
    assert len(records) == 2 * 4 * 3 * 2  # scenes, variants, targets, starts (given, predicted)
    assert all(r.status != "error" for r in records), [r.error for r in records]
    clean = [r for r in records if r.variant == "clean"]
    assert sum(r.success for r in clean) / len(clean) >= 0.8, printed
    assert sum(r.success for r in records) / len(records) >= 0.7, printed
    assert float(np.median([r.renders for r in clean])) <= 3
    predicted = [r for r in clean if not r.start_given]
    assert float(np.median([r.renders for r in predicted])) == 1, printed
    assert "reprojection, predicted start" in printed
    for r in records:
        assert r.renders == len({(t.lat, t.lon) for t in r.trajectory}) + r.after_renders
        # One render for the edges after the iterations, the reprojection strategy's only: for
        # an unconfirmed answer, or a confirmed one near a boundary or looking steeply down.
        assert r.after_renders <= 1
        assert r.after_renders == 0 or r.strategy == "reprojection"
        assert r.wall_ms >= r.stage_ms * 0.5
    profile = report["profile"]
    assert {row["scene"] for row in profile["rows"]} == {"demo", "garden", "all"}
    assert all(row["floor_p50_ms"] > 0 for row in profile["rows"])
    assert "median wall/floor" in printed
    assert (out / "renders_hist.png").stat().st_size > 0
    assert (out / "distance.png").stat().st_size > 0
    results = (tmp_path / "RESULTS.md").read_text()
    assert "#### Targets on-grid, clean" in results
    assert "wall / floor" in results


def _run(width, spp, outcomes, wall):
    records = [
        _record("reprojection", 2, success=ok, wall=wall, number=i, scene=scene)
        for i, (scene, ok) in enumerate(outcomes)
    ]
    return {"width": width, "spp": spp, "records": [r.model_dump(mode="json") for r in records]}


def test_the_render_setting_chosen_is_the_cheapest_that_loses_nothing():
    ok = [("demo", True)] * 10 + [("garden", True)] * 10
    one_miss = [("demo", False)] + ok[1:]
    runs = [
        _run(None, 16, ok, 300.0),
        _run(None, 8, ok, 200.0),
        _run(None, 4, one_miss, 150.0),  # cheaper, but one search fewer succeeds
        _run(160, 8, ok, 120.0),
    ]
    assert choose_setting(runs[:3]).startswith("scene px wide at 8 spp")
    # the reference is the largest film: a smaller one that loses nothing wins on cost
    assert choose_setting(runs).startswith("160 px wide at 8 spp")
    assert choose_setting([]) == ""


def test_sweep_matching_maps_a_smaller_film_onto_the_scene_film():
    truth = [
        ObjectAnnotation.model_validate(
            {
                "name": "a",
                "shape": "cube",
                "position": [0, 0, 0],
                "centroid": [0, 0, 0.5],
                "box": [40.0, 40.0, 120.0, 100.0],
                "visible_pixels": 4000,
                "full_box": [40.0, 40.0, 120.0, 100.0],
                "full_pixels": 4000,
                "visible_fraction": 1.0,
                "projected_center": [80.0, 70.0],
            }
        )
    ]
    half = Detection(label="cube", class_id=1, confidence=0.9, box=(20.0, 20.0, 60.0, 50.0))
    found, expected, correct, errors = _match([half], truth, fit((160, 120), (320, 240)))
    assert (found, expected, correct) == (1, 1, 1)
    assert errors == [pytest.approx(0.0)]


def test_predicted_start_searches_send_no_start_and_stand_apart_in_the_tables():
    from cosmos.bench.random_report import band_cells, band_table
    from cosmos.bench.runner import BenchTarget, _search_query, with_starts
    from cosmos.bench.stats import strategy_label
    from services.common.geometry.pose import Pose

    pose = Pose(theta_deg=30.0, phi_deg=0.0)
    index = GridIndex(lat=1, lon=0)
    target = BenchTarget(
        "demo", b"png", index, pose, start=index, start_pose=pose, seed=1, variant="clean", number=0
    )
    given, predicted = with_starts([target], ("given", "predicted"))
    assert "start_theta_deg" in _search_query(given, "reprojection", 10)
    query = _search_query(predicted, "reprojection", 10)
    assert "start_theta_deg" not in query
    assert "start_phi_deg" not in query
    records = [
        _record("reprojection", 3),
        _record("reprojection", 1).model_copy(update={"start_given": False}),
    ]
    labels = {s.strategy: s for s in summarize(records)}
    assert labels["reprojection"].renders_p50 == 3
    assert labels["reprojection, predicted start"].renders_p50 == 1
    assert [strategy_label(r) for r in records] == ["reprojection", "reprojection, predicted start"]
    table = band_table(band_cells(records, strategy_label), title="strategy")
    assert "reprojection, predicted start" in table
