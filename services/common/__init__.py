"""COSMOS 3D Search: what every service shares.

Importing the package caps what OpenCV may decode in this process, before any service module
imports cv2: OpenCV reads ``OPENCV_IO_MAX_IMAGE_PIXELS`` once, when it is loaded. A process that
loaded OpenCV earlier keeps its own cap, so :mod:`services.common.images` also checks the size in
the file header before decoding.
"""

from __future__ import annotations

import os

__all__ = ["HARD_MAX_IMAGE_PIXELS"]

HARD_MAX_IMAGE_PIXELS = 1 << 26
"""No image decoded by a service may have more pixels (8192 x 8192); settings go lower."""

os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(HARD_MAX_IMAGE_PIXELS))
