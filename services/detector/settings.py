"""Detector settings, read from ``COSMOS_*`` environment variables once per app."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, model_validator

from services.common import DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_UPLOAD_BYTES
from services.common.auth import ServiceTokenSettings
from services.common.bodies import (
    DEFAULT_BODY_TIMEOUT_S,
    DEFAULT_BODY_WAIT_S,
    DEFAULT_MIN_BYTES_PER_S,
    BodyLimits,
)
from services.common.catalog import BUILTIN_SCENES_DIR
from services.common.settings import split_paths
from services.detector import HARD_MAX_IMAGE_PIXELS

__all__ = ["DEFAULT_MODEL", "DetectorSettings"]

DEFAULT_MODEL = Path(__file__).resolve().parents[2] / "models" / "detector.onnx"
"""The shipped model; its sidecar (classes, provenance) is ``models/detector.json``."""

Fraction = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]


class DetectorSettings(ServiceTokenSettings):
    """``COSMOS_DETECTOR_MODEL`` names the general ONNX model (a sidecar ``<model>.json`` next to
    it, if present, supplies the class names and provenance); ``COSMOS_SCENES_DIR`` adds scene
    directories (as for the renderer), whose scenes' own models serve requests naming them; the
    rest tune inference and bound what one request may send."""

    detector_model: Path = DEFAULT_MODEL
    """The general ONNX model; class names from its metadata or ``<model>.json``."""
    scenes_dir: str = ""
    """Extra scene directories (as the renderer's), where scenes' own models are found."""
    detector_scene_check_s: Annotated[float, Field(ge=0.0, le=3600.0, allow_inf_nan=False)] = 1.0
    """How often at most a scene's model files are looked at for a new model (a request naming
    the scene, or ``GET /models``, looks); 0 looks every time."""
    detector_conf: Fraction = 0.25
    """Default confidence threshold (a request may override it with ``?conf=``)."""
    detector_iou: Annotated[float, Field(gt=0.0, le=1.0, allow_inf_nan=False)] = 0.5
    """Per-class NMS: a box overlapping a better one of its class by IoU above this is dropped."""
    detector_max_detections: Annotated[int, Field(ge=1, le=1000)] = 100
    """Boxes answered per image when a request gives no ``max_detections``."""
    detector_max_candidates: Annotated[int, Field(ge=1, le=100_000)] = 5000
    """Boxes over the threshold kept (best first) before NMS, which bounds its cost."""
    detector_threads: Annotated[int, Field(ge=0, le=256)] = 2
    """onnxruntime ``intra_op_num_threads``; 0 lets onnxruntime choose (one per core)."""
    detector_max_batch: Annotated[int, Field(ge=1, le=64)] = 8
    """Images per inference run when the model's batch dimension is dynamic."""
    detector_batch_window_ms: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    """How long the first image of a batch waits for company; 0 batches only what queued (a
    search's detections come one at a time, and requests that queue behind a running batch
    are still batched: the wait cost every search's detection ~1.5 ms, cosmos bench)."""
    detector_tiles: Annotated[int, Field(ge=0, le=4)] = 2
    """An image at least twice the network's input along both axes (a camera's photo, not a
    search's view) is also detected in an ``n x n`` grid of overlapping tiles, so that its small
    objects are seen ``n / 1.25`` times larger (:mod:`~services.detector.tiles`); 0 or 1: never."""
    detector_max_in_flight: Annotated[int, Field(ge=1, le=10_000)] = 64
    """Requests being decoded, queued or run at once; more get 503."""
    detector_max_decode_bytes: Annotated[int, Field(ge=1 << 20)] = 256 << 20
    """Decoded image bytes the requests in flight hold at once (each holds its image's width x
    height x max(3, channels x bytes per sample), from its header, from the decode until it is
    answered); more wait, and an image that alone needs more gets 413."""
    detector_decode_wait_s: Annotated[float, Field(ge=0.0, le=60.0, allow_inf_nan=False)] = 5.0
    """How long a request waits for decode bytes before it gets 503; 0 refuses at once."""
    detector_max_upload_bytes: Annotated[int, Field(ge=1024)] = (
        DEFAULT_MAX_UPLOAD_BYTES + 1024 * 1024
    )
    """Request body limit (the multipart body, so a little over the image itself)."""
    detector_body_budget_bytes: Annotated[int, Field(ge=1024)] | None = None
    """Request-body bytes held at once, before the decode budget applies
    (:mod:`services.common.bodies`): a request waits for its declared length before its body is
    read. Bodies up to 1/16 of the upload limit (search views) count in a lane of their own, a
    quarter of this, so they never wait behind large uploads. None: four maximal uploads."""
    detector_body_wait_s: Annotated[float, Field(ge=0, le=300, allow_inf_nan=False)] = (
        DEFAULT_BODY_WAIT_S
    )
    """How long a request waits for its body's bytes before a 503 (``Retry-After``)."""
    detector_body_timeout_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = (
        DEFAULT_BODY_TIMEOUT_S
    )
    """Seconds a body may take to arrive, plus its bytes at the rate below."""
    detector_body_min_bytes_per_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = (
        DEFAULT_MIN_BYTES_PER_S
    )
    """A body must arrive within ``timeout_s + bytes / min_bytes_per_s`` of its admission, else
    408 and the connection is closed."""
    detector_max_image_pixels: Annotated[int, Field(ge=64, le=HARD_MAX_IMAGE_PIXELS)] = (
        DEFAULT_MAX_IMAGE_PIXELS
    )
    """Decoded width x height, checked from the file header before anything is decoded."""
    detector_max_image_side: Annotated[int, Field(ge=8, le=65_535)] = 16_384
    """The longest side of an uploaded image, in pixels, read from its header."""
    detector_colour: bool = True
    """Measure each detection's colour (``Detection.color``); off leaves it null."""

    @model_validator(mode="after")
    def _an_image_of_the_largest_size_fits_the_decode_budget(self) -> DetectorSettings:
        smallest = self.detector_max_image_pixels * 3  # 8-bit RGB
        if self.detector_max_decode_bytes < smallest:
            raise ValueError(
                f"COSMOS_DETECTOR_MAX_DECODE_BYTES ({self.detector_max_decode_bytes}) is less than "
                f"one 8-bit RGB image of COSMOS_DETECTOR_MAX_IMAGE_PIXELS "
                f"({self.detector_max_image_pixels}) takes: {smallest} bytes"
            )
        self.body_limits()  # raises ValueError when a maximal upload does not fit the budget
        return self

    def body_limits(self) -> BodyLimits:
        """How request bodies are bounded: size, bytes in flight, time."""
        return BodyLimits.for_limit(
            self.detector_max_upload_bytes,
            budget_bytes=self.detector_body_budget_bytes,
            wait_s=self.detector_body_wait_s,
            timeout_s=self.detector_body_timeout_s,
            min_bytes_per_s=self.detector_body_min_bytes_per_s,
        )

    def scene_directories(self) -> list[Path]:
        """The directories searched for scene files, in order."""
        return [*split_paths(self.scenes_dir), BUILTIN_SCENES_DIR]
