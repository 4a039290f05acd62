"""The target image: the one ``Target`` of the operator's side.

A target is the picture a search is asked to place (the paper's target image): a render of a
scene from a pose, and the grid pose a search for it must answer. The fault suite's load, the
bench (:class:`~cosmos.bench.runner.BenchTarget` adds the start, seed and provenance of its
searches) and the standing benchmarks all search for targets of this one type.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from services.common.geometry.pose import GridIndex, Pose

__all__ = ["Target"]


@dataclass(frozen=True)
class Target:
    """A target image of ``scene``, rendered at ``pose``, whose search must find ``truth``."""

    scene: str
    image: bytes = field(repr=False)
    """The encoded image (PNG, or what a bench variant degraded it to)."""
    truth: GridIndex
    """The grid pose a search must answer: ``pose`` itself on the grid, else the nearest."""
    pose: Pose
    """The pose the image was rendered from."""
