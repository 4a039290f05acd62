"""A scene's own detector classes: one per object, look-alikes shared, labels within limits."""

from __future__ import annotations

from pathlib import Path

from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.geometry.scene import SceneSpec
from services.common.scene_models import class_label, model_dir, object_classes


def _spec(objects: list[dict]) -> SceneSpec:
    return SceneSpec.model_validate(
        {
            "camera": {"fov_deg": 45, "width": 320, "height": 240, "radius": 8.0},
            "lighting": {"point": {"position": [3, 3, 8], "intensity": 200}},
            "ground": {"size": 12.0, "color": [0.5, 0.5, 0.5]},
            "objects": objects,
        }
    )


def test_each_object_of_the_demo_is_its_own_class() -> None:
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get("demo")
    classes = object_classes(scene.spec)
    assert [c.label for c in classes] == [o.name for o in scene.spec.objects]
    assert all(c.shape == "sphere" and c.objects == (c.label,) for c in classes)
    assert model_dir(scene) == BUILTIN_SCENES_DIR / "demo.detector"


def test_identical_objects_share_a_class_and_yaw_does_not_matter() -> None:
    bale = {"shape": "cylinder", "radius": 0.5, "height": 0.8, "color": [0.8, 0.7, 0.2]}
    spec = _spec(
        [
            {"name": "bale1", "position": [1, 0], **bale},
            {"name": "post", "position": [0, 2], "shape": "cube", "size": 0.5, "color": [0, 0, 1]},
            {"name": "bale2", "position": [-1, 0], "yaw_deg": 40, **bale},
            # the same but 10 % taller: a detector can tell, so a class of its own
            {"name": "tall", "position": [2, 2], **{**bale, "height": 0.88}},
            # the same but another colour
            {"name": "red", "position": [-2, 2], **{**bale, "color": [0.9, 0.1, 0.1]}},
        ]
    )
    classes = object_classes(spec)
    assert [(c.label, c.objects) for c in classes] == [
        ("bale1+bale2", ("bale1", "bale2")),
        ("post", ("post",)),
        ("tall", ("tall",)),
        ("red", ("red",)),
    ]
    assert classes[0].shape == "cylinder"


def test_look_alike_is_transitive_and_textures_must_match() -> None:
    ball = {"shape": "sphere", "radius": 0.3}
    spec = _spec(
        [
            {"name": "a", "position": [1, 0], "color": [0.50, 0.5, 0.5], **ball},
            {"name": "b", "position": [0, 1], "color": [0.52, 0.5, 0.5], **ball},
            {"name": "c", "position": [-1, 0], "color": [0.54, 0.5, 0.5], **ball},
            {"name": "d", "position": [0, -1], "texture": "t.png", **ball},
        ]
    )
    assert [c.objects for c in object_classes(spec)] == [("a", "b", "c"), ("d",)]


def test_long_shared_labels_are_shortened_to_the_limit() -> None:
    names = [f"hay-bale-number-{i:02d}" for i in range(8)]
    label = class_label(names)
    assert len(label) <= 64
    assert label == "hay-bale-number-00+7"
    assert class_label(["x"]) == "x"


def test_model_dir_of_a_path() -> None:
    assert model_dir(Path("/s/field.yaml")) == Path("/s/field.detector")
