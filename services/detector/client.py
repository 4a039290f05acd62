"""A small synchronous client of the detector service."""

from __future__ import annotations

from types import TracebackType
from typing import Any

import cv2
import httpx
import numpy as np
from numpy.typing import NDArray

from services.common.models import DetectResponse, ModelInfo

__all__ = ["DetectorClient", "DetectorError"]


class DetectorError(RuntimeError):
    """The detector answered with an error (its problem detail is the message)."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"detector answered {status}: {detail}")
        self.status = status


def _media_type(data: bytes) -> str:
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "image/png"
    if data.startswith(b"\xff\xd8"):
        return "image/jpeg"
    return "application/octet-stream"


class DetectorClient:
    """Calls one detector at ``base_url`` with explicit timeouts."""

    def __init__(self, base_url: str, timeout_s: float = 60.0) -> None:
        self._http = httpx.Client(base_url=base_url, timeout=httpx.Timeout(timeout_s, connect=5.0))

    def __enter__(self) -> DetectorClient:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _check(self, response: httpx.Response) -> httpx.Response:
        if response.status_code >= 400:
            try:
                detail = str(response.json().get("detail", response.text))
            except ValueError:
                detail = response.text
            raise DetectorError(response.status_code, detail)
        return response

    def health(self) -> dict[str, Any]:
        """``GET /health``."""
        body: dict[str, Any] = self._check(self._http.get("/health")).json()
        return body

    def model(self) -> ModelInfo:
        """``GET /model``."""
        return ModelInfo.model_validate(self._check(self._http.get("/model")).json())

    def detect(
        self,
        image: bytes,
        *,
        conf: float | None = None,
        max_detections: int | None = None,
        filename: str = "image",
    ) -> DetectResponse:
        """``POST /detect`` with PNG or JPEG bytes."""
        params: dict[str, float | int] = {}
        if conf is not None:
            params["conf"] = conf
        if max_detections is not None:
            params["max_detections"] = max_detections
        files = {"image": (filename, image, _media_type(image))}
        response = self._check(self._http.post("/detect", files=files, params=params))
        return DetectResponse.model_validate(response.json())

    def detect_rgb(
        self,
        rgb: NDArray[np.uint8],
        *,
        conf: float | None = None,
        max_detections: int | None = None,
    ) -> DetectResponse:
        """``POST /detect`` with an RGB ``(H, W, 3)`` uint8 image, sent as PNG."""
        ok, buffer = cv2.imencode(
            ".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]
        )
        if not ok:
            raise ValueError("PNG encoding failed")
        return self.detect(
            bytes(buffer), conf=conf, max_detections=max_detections, filename="image.png"
        )
