"""The shared messages take numbers as numbers: a bool, a numeric string or an integer no int64
holds is refused, naming the field, where lax pydantic read ``true`` as 1 (a render at θ = 1)
and took ``class_id: 2**64``. JSON integers still count as numbers, and the form's text options
of a search are still read as numbers."""

from __future__ import annotations

import json
from typing import Any

import pytest
from pydantic import BaseModel, ValidationError

from services.common.base import MAX_SAFE_INTEGER
from services.common.contracts.detect import Detection, DetectResponse
from services.common.contracts.optimize import MapRequest, NextPoseRequest
from services.common.contracts.render import RenderRequest
from services.common.contracts.search import SearchOptions
from services.common.geometry.grid import GridSpec
from services.common.geometry.pose import GridIndex, Pose, PoseQuery

BOX = {"label": "sphere", "class_id": 0, "confidence": 0.9, "box": [1, 2, 30, 40]}
MODEL = {"name": "general", "classes": ["sphere"], "input_size": [640, 640], "sha256": "x"}
CAMERA = {"fov_deg": 60, "width": 320, "height": 240, "radius": 10}
TARGET = {"image_size": [320, 240], "detections": [BOX]}


def with_(document: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """``document`` (deep-copied) with the value at dotted ``path`` replaced by ``value``."""
    copy = json.loads(json.dumps(document))
    *parents, last = path.split(".")
    node: Any = copy
    for part in parents:
        node = node[int(part)] if part.isdigit() else node[part]
    node[int(last) if last.isdigit() else last] = value
    return copy


# (model, a valid JSON document, the numeric field to spoil, as a dotted path)
CASES = [
    (Pose, {"theta_deg": 45, "phi_deg": 30}, "theta_deg"),
    (Pose, {"theta_deg": 45, "phi_deg": 30}, "phi_deg"),
    (GridIndex, {"lat": 3, "lon": 5}, "lat"),
    (PoseQuery, {"lat": 3, "lon": 5}, "lon"),
    (RenderRequest, {"scene": "demo", "pose": {"theta_deg": 45, "phi_deg": 0}}, "pose.theta_deg"),
    (RenderRequest, {"scene": "demo", "pose": {"lat": 1, "lon": 0}, "spp": 4}, "spp"),
    (Detection, BOX, "class_id"),
    (Detection, BOX, "confidence"),
    (Detection, BOX, "box.2"),
    (DetectResponse, {"detections": [BOX], "image_size": [32, 24], "model": MODEL}, "image_size.0"),
    (GridSpec, {"angle_step_deg": 7.5, "min_theta_deg": 0, "max_theta_deg": 90}, "min_theta_deg"),
    (NextPoseRequest, {"scene": "demo", "target": TARGET}, "target.detections.0.box.0"),
    (NextPoseRequest, {"scene": "demo", "target": TARGET}, "target.image_size.1"),
    (
        NextPoseRequest,
        {"camera": CAMERA, "grid": {"angle_step_deg": 15}, "target": TARGET},
        "grid.angle_step_deg",
    ),
    (
        MapRequest,
        {"camera": CAMERA, "pose": {"theta_deg": 45, "phi_deg": 0}, "view": TARGET},
        "camera.width",
    ),
    (
        MapRequest,
        {"camera": CAMERA, "pose": {"theta_deg": 45, "phi_deg": 0}, "view": TARGET},
        "camera.radius",
    ),
]


@pytest.mark.parametrize(("model", "document", "path"), CASES)
def test_a_valid_message_is_read_as_before(model: type[BaseModel], document, path):
    model.model_validate_json(json.dumps(document))
    model.model_validate(document)


@pytest.mark.parametrize("spoiled", [True, False, "3", "nan", [3]])
@pytest.mark.parametrize(("model", "document", "path"), CASES)
def test_a_bool_or_a_string_is_not_a_number(model: type[BaseModel], document, path, spoiled):
    bad = with_(document, path, spoiled)
    for validate in (model.model_validate_json, model.model_validate):
        with pytest.raises(ValidationError) as refused:
            validate(json.dumps(bad) if validate == model.model_validate_json else bad)
        where = {".".join(str(part) for part in error["loc"]) for error in refused.value.errors()}
        assert any(loc.endswith(path) for loc in where), where


@pytest.mark.parametrize(
    ("model", "document", "path", "largest"),
    [
        (Detection, BOX, "class_id", 65535),
        (GridIndex, {"lat": 3, "lon": 5}, "lon", MAX_SAFE_INTEGER),
        (RenderRequest, {"scene": "d", "pose": {"lat": 1, "lon": 0}}, "seed", 2**31 - 1),
    ],
)
def test_integers_are_bounded(model: type[BaseModel], document, path, largest):
    model.model_validate_json(json.dumps(with_(document, path, largest)))
    for huge in (largest + 1, 2**63, 2**64):
        with pytest.raises(ValidationError):
            model.model_validate_json(json.dumps(with_(document, path, huge)))


def test_true_is_not_theta_one():
    """The issue's example: ``theta_deg: true`` rendered at θ = 1."""
    with pytest.raises(ValidationError, match="theta_deg"):
        RenderRequest.model_validate_json(
            '{"scene": "demo", "pose": {"theta_deg": true, "phi_deg": 0}}'
        )


def test_integers_are_numbers_and_a_search_form_s_text_is_read_as_numbers():
    assert Pose.model_validate_json('{"theta_deg": 45, "phi_deg": -90}') == Pose(
        theta_deg=45.0, phi_deg=270.0
    )
    options = SearchOptions.model_validate(
        {"scene": "demo", "start_theta_deg": "45", "start_phi_deg": "30", "seed": "7"}
    )
    assert (options.start_theta_deg, options.start_phi_deg, options.seed) == (45.0, 30.0, 7)
    for bad in ({"start_theta_deg": "91"}, {"start_theta_deg": "nan"}, {"seed": "-1"}):
        with pytest.raises(ValidationError):
            SearchOptions.model_validate({"scene": "demo", "start_phi_deg": "0", **bad})
