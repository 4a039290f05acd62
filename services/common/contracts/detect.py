"""Messages of the detector service: detections, the models that make them, health."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from services.common.base import BoxXYXY, FrozenModel, Integer, NonNegInt, Number

__all__ = [
    "DetectResponse",
    "Detection",
    "DetectorHealth",
    "DetectorModels",
    "ModelInfo",
    "SceneModelState",
    "SceneModelStatus",
]


Channel255 = Annotated[Number, Field(ge=0.0, le=255.0)]
Rgb255 = tuple[Channel255, Channel255, Channel255]

MAX_CLASS_ID = 65535
"""The largest class id a detection may carry (a model has far fewer classes)."""


class Detection(FrozenModel):
    """One object found in an image.

    ``box`` is ``[x1, y1, x2, y2]`` in pixels of the image that was sent (pixel edges: the box of
    a single pixel at column 3, row 5 is ``[3, 5, 4, 6]``). ``color`` is the mean sRGB colour
    (0–255) of the object's own pixels inside the box, ground excluded, or null when it could not
    be measured.
    """

    label: Annotated[str, Field(min_length=1, max_length=64)]
    class_id: Annotated[Integer, Field(ge=0, le=MAX_CLASS_ID)]
    confidence: Annotated[Number, Field(ge=0.0, le=1.0)]
    box: BoxXYXY
    color: Rgb255 | None = None


class ModelInfo(FrozenModel):
    """The detector model a service runs."""

    name: str
    classes: tuple[str, ...]
    input_size: tuple[Integer, Integer] = Field(
        description="Network input (width, height) in pixels."
    )
    sha256: str
    provenance: dict[str, str | Integer | Number] = Field(default_factory=dict)
    scene: str | None = Field(
        default=None,
        description="The scene this model was onboarded for (its classes are that scene's "
        "objects); null for the general model, whose classes are shape types.",
    )


class DetectResponse(FrozenModel):
    """``POST /detect``: the detections and the size (width, height) of the image they refer to."""

    detections: tuple[Detection, ...]
    image_size: tuple[Integer, Integer]
    model: ModelInfo
    inference_ms: Annotated[Number, Field(ge=0.0)] = 0.0


class DetectorHealth(FrozenModel):
    """``GET /health`` of the detector."""

    status: Literal["ok"]
    service: Literal["detector"]
    model: str
    model_sha256: str
    in_flight: NonNegInt
    providers: tuple[str, ...] = Field(description="onnxruntime execution providers in use.")
    intra_op_threads: NonNegInt = Field(
        description="onnxruntime intra-op threads (0: one per core)."
    )
    max_batch: Annotated[Integer, Field(ge=1)] = Field(description="Images per inference run.")
    batches_run: NonNegInt
    images_run: NonNegInt
    scene_models: NonNegInt = Field(
        default=0, description="Scenes whose own model is serving (see GET /models)."
    )
    decode_bytes: NonNegInt = Field(
        default=0, description="Bytes of decoded images the requests in flight hold now."
    )
    decode_bytes_peak: NonNegInt = Field(
        default=0, description="The most bytes of decoded images held at once since start."
    )
    max_decode_bytes: NonNegInt = Field(
        default=0, description="The decode budget: more bytes than this are never held at once."
    )


SceneModelState = Literal["serving", "refused", "none"]


class SceneModelStatus(FrozenModel):
    """One scene's own detector as the detector service sees it."""

    scene: str
    state: SceneModelState = Field(
        description="The scene's newest model file: `serving` (validated and in use), `refused` "
        "(unloadable, or its sha256, scene or classes do not match: see `error`), `none` (the "
        "scene has no model)."
    )
    model: ModelInfo | None = Field(
        default=None,
        description="The scene model answering this scene's requests: the newest when serving, "
        "the previous one when the newest was refused; null when the general model serves it.",
    )
    error: str | None = Field(default=None, description="Why the newest model was refused.")
    classes: NonNegInt = Field(
        description="Classes a model of this scene must have: one per object, look-alikes shared."
    )


class DetectorModels(FrozenModel):
    """``GET /models``: the general model and every scene's own model."""

    general: ModelInfo
    scenes: tuple[SceneModelStatus, ...]
