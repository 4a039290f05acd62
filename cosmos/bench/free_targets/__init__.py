"""Free targets for the bench (issue 23, item 5): cameras drawn as drones take photos, their
images and ground truth, and the two references a free search is measured against: a plain
``cv2.solvePnPRansac`` baseline and the ideal box-only fit; and the box solver
(:mod:`services.optimizer.free`) measured beside them.

:mod:`.draw` draws and renders the targets (through :mod:`.rendering`), :mod:`.shapes` holds the
objects' hull points and projects their boxes, :mod:`.solve` has the baseline and the box-only
fit, :mod:`.solver` feeds the box solver a target's boxes and counts its confirmed-wrong
answers, :mod:`.metrics` the errors and shares, :mod:`.report` runs all three on targets and
lays out the tables per elevation band (``python -m cosmos.bench.free_targets``).
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
from cosmos.bench.free_targets.report import TargetResult, evaluate, solver_table, text_table
from cosmos.bench.free_targets.shapes import SceneShapes, project_boxes, scene_shapes
from cosmos.bench.free_targets.solve import baseline, baseline_pnp, box_fit, box_only_bound
from cosmos.bench.free_targets.solver import (
    SOLVER,
    answer_estimate,
    confirmed_wrong,
    solve_target,
    target_detections,
)

__all__ = [
    "BANDS",
    "FREE_VARIANTS",
    "SOLVER",
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
    "answer_estimate",
    "baseline",
    "baseline_pnp",
    "box_fit",
    "box_only_bound",
    "confirmed_wrong",
    "draw_targets",
    "evaluate",
    "pose_error",
    "project_boxes",
    "scene_shapes",
    "solve_target",
    "solver_table",
    "summarize",
    "target_detections",
    "text_table",
    "usable_objects",
]
