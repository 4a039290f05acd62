"""Plots of a search, like the paper's figures (matplotlib, off-screen).

* :func:`trajectory_png` (Fig. 6): the hemisphere seen from above — polar radius θ, angle φ — with
  the grid poses, the start, the visited poses in order and the estimate;
* :func:`distance_png` (Fig. 8): the angle between each visited pose and the estimate, per
  iteration.

Drawing one takes ~0.4 s of CPU; :class:`PlotCache` keeps those of finished searches.
"""

from __future__ import annotations

import io
import math
from collections.abc import Awaitable, Callable

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402 - after choosing the off-screen backend
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from services.common.caches import LruFront, SharedLru  # noqa: E402
from services.common.contracts.search import TERMINAL_STATUSES, Search  # noqa: E402
from services.common.geometry.grid import HemisphereGrid  # noqa: E402
from services.common.geometry.sphere import angular_distance_deg  # noqa: E402

__all__ = ["PlotCache", "distance_png", "trajectory_png"]


def _png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def trajectory_png(search: Search, grid: HemisphereGrid) -> bytes:
    """The path of the camera on the hemisphere (view from above the zenith)."""
    fig = plt.figure(figsize=(5.2, 5.2))
    ax = fig.add_subplot(projection="polar")
    ax.scatter(np.radians(grid.phi_deg), grid.theta_deg, s=4, c="#cccccc", label="grid poses")
    poses = [it.pose for it in search.iterations]
    if poses:
        phis = np.radians([p.phi_deg for p in poses])
        thetas = [p.theta_deg for p in poses]
        ax.plot(phis, thetas, "-o", c="#1f77b4", ms=4, lw=1.2, label="visited")
    if search.mode == "hemisphere":  # a free search starts where the optimizer solved for
        ax.scatter(
            [math.radians(search.start.phi_deg)],
            [search.start.theta_deg],
            s=60,
            c="#2ca02c",
            marker="s",
            label="start",
            zorder=3,
        )
    if search.result is not None:
        refined = search.result.refined_pose
        ax.scatter(
            [math.radians(refined.phi_deg)],
            [refined.theta_deg],
            s=140,
            c="#d62728",
            marker="*",
            label="estimate",
            zorder=4,
        )
    ax.set_ylim(0, 90)
    ax.set_title(f"search {search.id[:8]} — {search.strategy}, {len(poses)} renders", fontsize=10)
    ax.legend(loc="lower left", bbox_to_anchor=(-0.1, -0.12), fontsize=8, ncol=4)
    return _png(fig)


def distance_png(search: Search) -> bytes:
    """Angle (degrees) between each visited pose and the final (or latest) estimate."""
    fig, ax = plt.subplots(figsize=(5.6, 3.4))
    target = search.result.refined_pose if search.result is not None else None
    if target is None:
        estimates = [it.estimate for it in search.iterations if it.estimate is not None]
        target = estimates[-1] if estimates else None
    if target is not None and search.iterations:
        distances = [
            float(angular_distance_deg((it.pose.theta_deg, it.pose.phi_deg), target))
            for it in search.iterations
        ]
        ax.plot(range(len(distances)), distances, "-o", c="#1f77b4", ms=4)
    ax.set_xlabel("iteration (rendered view)")
    ax.set_ylabel("angle to the estimate (°)")
    ax.set_title(f"search {search.id[:8]}: distance to the estimate", fontsize=10)
    ax.grid(alpha=0.3)
    return _png(fig)


class PlotCache(LruFront[bytes]):
    """The plots of finished searches, the ``capacity`` most recently used ones (a
    :class:`~services.common.caches.SharedLru` bounded by count).

    A running search's plots change with every iteration: they are drawn on every request. A
    finished search's are drawn once; its ``updated_at`` is part of the key, so a search that
    runs again (a retry) and finishes anew is drawn anew.
    """

    def __init__(self, capacity: int = 64) -> None:
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self.capacity = capacity
        self._lru = SharedLru[bytes](capacity)

    async def png(self, search: Search, name: str, draw: Callable[[], Awaitable[bytes]]) -> bytes:
        """Plot ``name`` of ``search``: kept if the search is finished, else ``draw()``."""
        if search.status not in TERMINAL_STATUSES:
            return await draw()
        key = (search.id, name, search.updated_at)
        png = self._lru.lookup(key)
        if png is None:
            png = await draw()
            self._lru.put(key, png)
        return png
