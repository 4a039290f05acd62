"""The scene catalog: directory order, invalid files, unknown ids, re-reading and rescanning."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import pytest

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.errors import NotFoundError, UnprocessableError
from services.renderer.settings import RendererSettings

ROOT = Path(__file__).resolve().parents[2]


def scene_text(radius: float = 8.0, name: str = "ball") -> str:
    """A small valid scene without assets; ``radius`` tells versions and copies apart."""
    return f"""\
camera: {{fov_deg: 45, width: 320, height: 240, radius: {radius}}}
lighting: {{point: {{position: [3.0, 3.0, 8.0], intensity: 200.0}}}}
ground: {{size: 12.0, color: [0.5, 0.5, 0.5]}}
objects:
  - {{name: {name}, shape: sphere, position: [0.0, 0.0], radius: 0.5}}
"""


INVALID_TEXT = scene_text().replace("radius: 0.5", "radius: -0.5")


def write(path: Path, text: str, *, mtime_ns: int | None = None) -> Path:
    """Write ``text``; with ``mtime_ns`` pin the modification time, so a rewrite is seen (or
    hidden) regardless of the file system's timestamp resolution."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    if mtime_ns is not None:
        os.utime(path, ns=(mtime_ns, mtime_ns))
    return path


@pytest.fixture(autouse=True)
def _no_scenes_dir_from_the_environment(monkeypatch):
    monkeypatch.delenv("COSMOS_SCENES_DIR", raising=False)


# -- built-in scenes and directory order -------------------------------------------------------


def test_builtin_directory_is_the_repos_scenes_folder():
    assert BUILTIN_SCENES_DIR == ROOT / "scenes"
    assert (BUILTIN_SCENES_DIR / "demo.yaml").is_file()


def test_builtin_catalog_holds_demo_and_garden():
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    assert catalog.ids() == ["demo", "garden"]
    assert catalog.invalid() == {}
    demo = catalog.get("demo")
    assert demo.id == "demo"
    assert demo.path == BUILTIN_SCENES_DIR / "demo.yaml"
    assert demo.spec.search.grid().size == 341  # Δ = 7.5° over θ ∈ [7.5°, 82.5°]
    garden = catalog.get("garden")
    assert set(garden.assets) == {
        "ground.texture",
        "objects[1].texture",
        "objects[3].file",
        "objects[3].texture",
        "objects[5].file",
    }


def test_first_directory_wins_for_a_duplicate_id(tmp_path):
    first = write(tmp_path / "a" / "twin.yaml", scene_text(radius=8.0))
    second = write(tmp_path / "b" / "twin.yaml", scene_text(radius=9.0))
    catalog = SceneCatalog([first.parent, second.parent])
    assert catalog.ids() == ["twin"]
    assert catalog.get("twin").path == first
    assert catalog.get("twin").spec.camera.radius == 8.0
    reversed_catalog = SceneCatalog([second.parent, first.parent])
    assert reversed_catalog.get("twin").path == second
    assert reversed_catalog.get("twin").spec.camera.radius == 9.0


def test_scenes_from_all_directories_are_merged(tmp_path):
    write(tmp_path / "a" / "one.yaml", scene_text())
    write(tmp_path / "b" / "two.yaml", scene_text())
    catalog = SceneCatalog([tmp_path / "a", tmp_path / "b", BUILTIN_SCENES_DIR])
    assert catalog.ids() == ["demo", "garden", "one", "two"]


def test_settings_search_scenes_dir_entries_before_the_builtin_one(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    settings = RendererSettings(scenes_dir=f"{a}{os.pathsep}{os.pathsep}{b}{os.pathsep}")
    assert settings.scene_directories() == [a, b, BUILTIN_SCENES_DIR]
    assert RendererSettings().scene_directories() == [BUILTIN_SCENES_DIR]


def test_scenes_dir_from_the_environment(monkeypatch, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    monkeypatch.setenv("COSMOS_SCENES_DIR", f"{a}{os.pathsep}{b}")
    assert RendererSettings().scene_directories() == [a, b, BUILTIN_SCENES_DIR]


def test_override_directory_from_settings_replaces_a_builtin_scene(tmp_path):
    override = tmp_path / "override"
    write(override / "demo.yaml", scene_text(radius=11.0))
    write(override / "extra.yaml", scene_text())
    catalog = SceneCatalog(RendererSettings(scenes_dir=str(override)).scene_directories())
    assert catalog.ids() == ["demo", "extra", "garden"]
    assert catalog.get("demo").path == override / "demo.yaml"
    assert catalog.get("demo").spec.camera.radius == 11.0
    assert catalog.get("garden").path == BUILTIN_SCENES_DIR / "garden.yaml"


def test_invalid_override_shadows_the_builtin_scene(tmp_path):
    # The first file wins even when it is broken: the operator sees its error, not a silent
    # fallback to a different scene of the same name.
    write(tmp_path / "demo.yaml", INVALID_TEXT)
    catalog = SceneCatalog([tmp_path, BUILTIN_SCENES_DIR])
    assert "demo" not in catalog.ids()
    assert set(catalog.invalid()) == {"demo"}
    with pytest.raises(UnprocessableError):
        catalog.get("demo")


def test_missing_directory_is_skipped_with_a_warning(tmp_path, caplog):
    write(tmp_path / "here" / "one.yaml", scene_text())
    with caplog.at_level(logging.WARNING, logger="cosmos.renderer"):
        catalog = SceneCatalog([tmp_path / "absent", tmp_path / "here"])
    assert catalog.ids() == ["one"]
    assert any("does not exist" in r.getMessage() for r in caplog.records)


def test_only_yaml_files_are_scenes(tmp_path):
    write(tmp_path / "short.yml", scene_text())
    write(tmp_path / "notes.txt", scene_text())
    write(tmp_path / "data.json", "{}")
    write(tmp_path / "upper.YAML", scene_text())
    (tmp_path / "folder.yaml").mkdir()
    catalog = SceneCatalog([tmp_path])
    assert catalog.ids() == ["short"]
    assert catalog.invalid() == {}


def test_yaml_beats_yml_for_the_same_id_in_one_directory(tmp_path):
    write(tmp_path / "same.yml", scene_text(radius=9.0))
    write(tmp_path / "same.yaml", scene_text(radius=8.0))
    assert SceneCatalog([tmp_path]).get("same").path == tmp_path / "same.yaml"


# -- invalid files and unknown ids -------------------------------------------------------------


def test_invalid_file_is_listed_and_get_answers_with_its_error(tmp_path):
    write(tmp_path / "good.yaml", scene_text())
    bad = write(tmp_path / "bad.yaml", INVALID_TEXT)
    catalog = SceneCatalog([tmp_path])
    assert catalog.ids() == ["good"]
    invalid = catalog.invalid()
    assert list(invalid) == ["bad"]
    assert invalid["bad"].startswith(f"{bad}: objects[0].radius: ")
    with pytest.raises(UnprocessableError) as info:
        catalog.get("bad")
    error = info.value
    assert error.status == 422
    assert error.field == "scene"
    assert error.slug == "invalid-scene-file"
    assert error.detail == invalid["bad"]
    assert catalog.get("good").id == "good"  # one bad file does not spoil the others


def test_file_with_a_bad_stem_is_listed_invalid(tmp_path):
    write(tmp_path / "two words.yaml", scene_text())
    catalog = SceneCatalog([tmp_path])
    assert catalog.ids() == []
    assert "(the file stem) is not allowed" in catalog.invalid()["two words"]
    with pytest.raises(UnprocessableError):
        catalog.get("two words")


def test_file_with_a_missing_asset_is_listed_invalid(tmp_path):
    text = scene_text().replace("color: [0.5, 0.5, 0.5]", "texture: textures/none.png")
    write(tmp_path / "bare.yaml", text)
    catalog = SceneCatalog([tmp_path])
    assert (
        "ground.texture: asset file 'textures/none.png' does not exist"
        in (catalog.invalid()["bare"])
    )


def test_unusable_asset_path_does_not_break_the_catalog(tmp_path):
    write(tmp_path / "good.yaml", scene_text())
    text = scene_text().replace("color: [0.5, 0.5, 0.5]", 'texture: "a\\0b.png"')
    write(tmp_path / "nul.yaml", text)
    catalog = SceneCatalog([tmp_path])  # must not raise: one bad file cannot stop the service
    assert catalog.ids() == ["good"]
    assert list(catalog.invalid()) == ["nul"]
    with pytest.raises(UnprocessableError, match=r"ground\.texture"):
        catalog.get("nul")


@pytest.mark.parametrize("scene_id", ["nope", "Demo", "demo.yaml", "../scenes/demo", "", "a b"])
def test_unknown_id_raises_not_found(scene_id):
    catalog = SceneCatalog([BUILTIN_SCENES_DIR])
    with pytest.raises(NotFoundError) as info:
        catalog.get(scene_id)
    error = info.value
    assert error.status == 404
    assert error.field == "scene"
    assert error.slug == "unknown-scene"
    assert "known: demo, garden" in error.detail


def test_not_found_lists_none_when_there_are_no_valid_scenes(tmp_path):
    with pytest.raises(NotFoundError, match=r"known: none"):
        SceneCatalog([tmp_path]).get("demo")


# -- re-reading and rescanning -----------------------------------------------------------------


def test_changed_file_is_read_again(tmp_path):
    path = write(tmp_path / "live.yaml", scene_text(radius=8.0), mtime_ns=1_000_000_000_000)
    catalog = SceneCatalog([tmp_path])
    first = catalog.get("live")
    assert first.spec.camera.radius == 8.0
    assert first.version == 1_000_000_000_000
    write(path, scene_text(radius=9.5), mtime_ns=2_000_000_000_000)
    second = catalog.get("live")
    assert second.spec.camera.radius == 9.5
    assert second.version == 2_000_000_000_000


def test_unchanged_file_is_served_from_the_cache(tmp_path):
    path = write(tmp_path / "live.yaml", scene_text(radius=8.0), mtime_ns=1_000_000_000_000)
    catalog = SceneCatalog([tmp_path])
    first = catalog.get("live")
    assert catalog.get("live") is first
    # Same modification time: the catalog trusts its copy and does not read the file.
    write(path, scene_text(radius=9.5), mtime_ns=1_000_000_000_000)
    assert catalog.get("live") is first


def test_file_turning_invalid_and_back(tmp_path):
    path = write(tmp_path / "flaky.yaml", scene_text(), mtime_ns=1_000_000_000_000)
    catalog = SceneCatalog([tmp_path])
    assert catalog.get("flaky").spec.camera.radius == 8.0

    write(path, INVALID_TEXT, mtime_ns=2_000_000_000_000)
    with pytest.raises(UnprocessableError, match=r"objects\[0\]\.radius"):
        catalog.get("flaky")
    assert catalog.ids() == []
    assert list(catalog.invalid()) == ["flaky"]

    write(path, scene_text(radius=12.0), mtime_ns=3_000_000_000_000)
    assert catalog.get("flaky").spec.camera.radius == 12.0
    assert catalog.ids() == ["flaky"]
    assert catalog.invalid() == {}


def test_new_file_is_found_by_get(tmp_path):
    catalog = SceneCatalog([tmp_path, BUILTIN_SCENES_DIR])
    write(tmp_path / "fresh.yaml", scene_text())
    assert "fresh" not in catalog.ids()  # nothing has looked yet
    assert catalog.get("fresh").path == tmp_path / "fresh.yaml"
    assert catalog.ids() == ["demo", "fresh", "garden"]


def test_new_invalid_file_is_found_by_get(tmp_path):
    catalog = SceneCatalog([tmp_path])
    write(tmp_path / "fresh.yaml", INVALID_TEXT)
    with pytest.raises(UnprocessableError):
        catalog.get("fresh")
    assert list(catalog.invalid()) == ["fresh"]


def test_rescan_picks_up_a_new_override(tmp_path):
    catalog = SceneCatalog([tmp_path, BUILTIN_SCENES_DIR])
    assert catalog.get("demo").path == BUILTIN_SCENES_DIR / "demo.yaml"
    write(tmp_path / "demo.yaml", scene_text(radius=10.0))
    catalog.rescan()
    assert catalog.get("demo").path == tmp_path / "demo.yaml"
    assert catalog.get("demo").spec.camera.radius == 10.0


def test_rescan_forgets_removed_files(tmp_path):
    path = write(tmp_path / "gone.yaml", scene_text())
    bad = write(tmp_path / "bad.yaml", INVALID_TEXT)
    catalog = SceneCatalog([tmp_path])
    assert (catalog.ids(), list(catalog.invalid())) == (["gone"], ["bad"])
    path.unlink()
    bad.unlink()
    catalog.rescan()
    assert (catalog.ids(), catalog.invalid()) == ([], {})
    with pytest.raises(NotFoundError):
        catalog.get("gone")


def test_deleted_override_falls_back_to_the_builtin_scene(tmp_path):
    override = write(tmp_path / "demo.yaml", scene_text(radius=10.0))
    catalog = SceneCatalog([tmp_path, BUILTIN_SCENES_DIR])
    assert catalog.get("demo").path == override
    override.unlink()
    assert catalog.get("demo").path == BUILTIN_SCENES_DIR / "demo.yaml"


def test_deleted_scene_is_not_found(tmp_path):
    path = write(tmp_path / "gone.yaml", scene_text())
    catalog = SceneCatalog([tmp_path])
    path.unlink()
    with pytest.raises(NotFoundError):
        catalog.get("gone")


def test_copied_builtin_scene_with_assets_loads_from_its_new_folder(tmp_path):
    shutil.copytree(BUILTIN_SCENES_DIR, tmp_path / "scenes")
    catalog = SceneCatalog([tmp_path / "scenes", BUILTIN_SCENES_DIR])
    garden = catalog.get("garden")
    assert garden.path == tmp_path / "scenes" / "garden.yaml"
    assert all(p.is_relative_to((tmp_path / "scenes").resolve()) for p in garden.assets.values())
