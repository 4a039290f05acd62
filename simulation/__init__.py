"""COSMOS 3D Search: an offline stand-in for the renderer and the detector.

:class:`~.detections.SceneSimulator` gives synthetic detections of a scene's objects from any
hemisphere pose (point clouds on their surfaces, :mod:`.surfaces`), with a seeded
:class:`~.detections.NoiseModel`; :func:`~.search.run_search` plays a next-best-pose strategy on
them. Tests and ``benchmarks/`` use it; the services do not.
"""

from simulation.detections import (
    CLASSES,
    OCCLUSION_CELL_PX,
    NoiseModel,
    SceneSimulator,
    SimulatedViews,
)
from simulation.search import SearchOutcome, run_search
from simulation.surfaces import srgb8

__all__ = [
    "CLASSES",
    "OCCLUSION_CELL_PX",
    "NoiseModel",
    "SceneSimulator",
    "SearchOutcome",
    "SimulatedViews",
    "run_search",
    "srgb8",
]
