"""COSMOS 3D Search: detector. Finds the scene's objects in an image with a YOLO-format ONNX model.

The cap on decoded image pixels is set by :mod:`services.common` (imported first).
"""

from __future__ import annotations

from services.common import HARD_MAX_IMAGE_PIXELS

__all__ = ["HARD_MAX_IMAGE_PIXELS"]
