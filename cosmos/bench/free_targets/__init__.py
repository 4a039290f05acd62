"""Free targets for the bench (issue 23, item 5): cameras drawn as drones take photos, their
images and ground truth, and the two references a free search is measured against: a plain
``cv2.solvePnPRansac`` baseline and the ideal box-only fit.

:mod:`.draw` draws and renders the targets (through :mod:`.rendering`), :mod:`.shapes` holds the
objects' hull points and projects their boxes, :mod:`.solve` has the baseline and the box-only
fit, :mod:`.metrics` the errors and shares, :mod:`.report` runs both references on targets and
lays out the table per elevation band (``python -m cosmos.bench.free_targets``).
"""

from cosmos.bench.free_targets.draw import (
    BANDS,
    FREE_VARIANTS,
    DrawError,
    DrawnCamera,
    FreeTarget,
    draw_targets,
    usable_objects,
)
from cosmos.bench.free_targets.estimate import Estimate
from cosmos.bench.free_targets.metrics import (
    THRESHOLDS,
    ErrorSummary,
    PoseError,
    pose_error,
    summarize,
)
from cosmos.bench.free_targets.rendering import LocalRenderer, Renderer
from cosmos.bench.free_targets.report import TargetResult, evaluate, text_table
from cosmos.bench.free_targets.shapes import SceneShapes, project_boxes, scene_shapes
from cosmos.bench.free_targets.solve import baseline, baseline_pnp, box_fit, box_only_bound

__all__ = [
    "BANDS",
    "FREE_VARIANTS",
    "THRESHOLDS",
    "DrawError",
    "DrawnCamera",
    "ErrorSummary",
    "Estimate",
    "FreeTarget",
    "LocalRenderer",
    "PoseError",
    "Renderer",
    "SceneShapes",
    "TargetResult",
    "baseline",
    "baseline_pnp",
    "box_fit",
    "box_only_bound",
    "draw_targets",
    "evaluate",
    "pose_error",
    "project_boxes",
    "scene_shapes",
    "summarize",
    "text_table",
    "usable_objects",
]
