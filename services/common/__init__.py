"""COSMOS 3D Search: what every service shares.

Importing the package caps what OpenCV may decode in this process, before any service module
imports cv2: OpenCV reads ``OPENCV_IO_MAX_IMAGE_PIXELS`` once, when it is loaded. A process that
loaded OpenCV earlier keeps its own cap, so :mod:`services.common.images` also checks the size in
the file header before decoding.
"""

from __future__ import annotations

import os

__all__ = ["DEFAULT_MAX_IMAGE_PIXELS", "DEFAULT_MAX_UPLOAD_BYTES", "HARD_MAX_IMAGE_PIXELS"]

HARD_MAX_IMAGE_PIXELS = 1 << 26
"""No image decoded by a service may have more pixels (8192 x 8192); settings go lower."""
DEFAULT_MAX_IMAGE_PIXELS = 8192 * 6144
"""The services' default limit on a target's pixels (50.3 MP): the photos of the drone cameras
users fly fit, 48 MP (8064 x 6048), 45 MP (8192 x 5460) and 20 MP (5472 x 3648) alike. A JPEG
that large is decoded already shrunk (:func:`services.common.images.decode_image`)."""
DEFAULT_MAX_UPLOAD_BYTES = 48 * 1024 * 1024
"""The services' default limit on an uploaded target, in bytes: a 48 MP camera JPEG takes
15-30 MB."""

os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(HARD_MAX_IMAGE_PIXELS))
