"""The optimizer's composition root: :func:`build_optimizer`, used by its app, the bench and
the benchmarks alike, so that what the service is made of is wired once."""

from __future__ import annotations

from services.common.catalog import SceneCatalog
from services.optimizer.calibration import CalibrationStore
from services.optimizer.planning import OptimizerContext
from services.optimizer.settings import OptimizerSettings

__all__ = ["build_optimizer"]


def build_optimizer(settings: OptimizerSettings) -> OptimizerContext:
    """The optimizer's parts, wired once: the calibrations and the scene catalog (read from
    disk), and the bounds of its requests."""
    return OptimizerContext(
        calibrations=CalibrationStore.load(settings.optimizer_paper_calibration),
        catalog=SceneCatalog(settings.scene_directories()),
        default_strategy=settings.optimizer_default_strategy,
        max_grid_poses=settings.optimizer_max_grid_poses,
        max_history_detections=settings.optimizer_max_history_detections,
    )
