"""A small synchronous client of the detector service."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.client import ServiceCallError, ServiceClient
from services.common.contracts.detect import DetectorModels, DetectResponse, ModelInfo
from services.common.images import media_type_of

__all__ = ["DetectorClient", "DetectorError"]


class DetectorError(ServiceCallError):
    """The detector answered with an error."""


class DetectorClient(ServiceClient):
    """Calls one detector at ``base_url`` with explicit timeouts."""

    service = "detector"
    error = DetectorError

    def health(self) -> dict[str, Any]:
        """``GET /health``."""
        body: dict[str, Any] = self._check(self._http.get("/health")).json()
        return body

    def model(self) -> ModelInfo:
        """``GET /model``: the general model."""
        return ModelInfo.model_validate(self._check(self._http.get("/model")).json())

    def models(self) -> DetectorModels:
        """``GET /models``: the general model and every scene's own."""
        return DetectorModels.model_validate(self._check(self._http.get("/models")).json())

    def detect(
        self,
        image: bytes,
        *,
        conf: float | None = None,
        max_detections: int | None = None,
        filename: str = "image",
        scene: str | None = None,
    ) -> DetectResponse:
        """``POST /detect`` with PNG, JPEG or binary PPM bytes; ``scene`` asks for that scene's
        own model (the general model answers when it has none)."""
        params: dict[str, float | int | str] = {}
        if scene is not None:
            params["scene"] = scene
        if conf is not None:
            params["conf"] = conf
        if max_detections is not None:
            params["max_detections"] = max_detections
        files = {"image": (filename, image, media_type_of(image))}
        response = self._check(self._http.post("/detect", files=files, params=params))
        return DetectResponse.model_validate(response.json())

    def detect_rgb(
        self,
        rgb: NDArray[np.uint8],
        *,
        conf: float | None = None,
        max_detections: int | None = None,
        scene: str | None = None,
    ) -> DetectResponse:
        """``POST /detect`` with an RGB ``(H, W, 3)`` uint8 image, sent as PNG."""
        ok, buffer = cv2.imencode(
            ".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]
        )
        if not ok:
            raise ValueError("PNG encoding failed")
        return self.detect(
            bytes(buffer),
            conf=conf,
            max_detections=max_detections,
            filename="image.png",
            scene=scene,
        )
