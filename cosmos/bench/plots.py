"""The bench's plots (matplotlib, Agg, imported when drawing): renders per search, and the
angle to the true pose per iteration (the paper's Fig. 8).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cosmos.bench.runner import SearchRecord
from cosmos.bench.stats import STRATEGY_ORDER, ranked, strategy_label
from cosmos.bench.variants import VARIANTS

__all__ = ["write_plots"]


def write_plots(records: Sequence[SearchRecord], out: Path) -> list[Path]:
    """``renders_hist.png`` (renders per search, per strategy and variant) and
    ``distance.png`` (angle from the camera to the true pose per iteration, clean on-grid
    targets, like the paper's Fig. 8). Returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    strategies = ranked((strategy_label(r) for r in records), STRATEGY_ORDER)
    written: list[Path] = []
    if not strategies:
        return written

    fig, axes = plt.subplots(
        1, len(strategies), figsize=(4.2 * len(strategies), 3.4), squeeze=False
    )
    for ax, strategy in zip(axes[0], strategies, strict=True):
        mine = [r for r in records if strategy_label(r) == strategy and r.status != "error"]
        top = max((r.renders for r in mine), default=1)
        bins = np.arange(0.5, top + 1.5, 1.0)
        for variant in VARIANTS:
            values = [r.renders for r in mine if r.variant == variant]
            if values:
                ax.hist(values, bins=bins, histtype="step", linewidth=1.5, label=variant)
        ax.set_title(strategy)
        ax.set_xlabel("renders per search (start view included)")
        ax.set_ylabel("searches")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "renders_hist.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    fig, axes = plt.subplots(
        1, len(strategies), figsize=(4.2 * len(strategies), 3.4), squeeze=False, sharey=True
    )
    for ax, strategy in zip(axes[0], strategies, strict=True):
        mine = [r for r in records if strategy_label(r) == strategy and r.variant == "clean"]
        curves = [[t.distance_deg for t in r.trajectory] for r in mine if r.trajectory]
        for curve in curves:
            ax.plot(range(1, len(curve) + 1), curve, color="0.6", linewidth=0.6, alpha=0.5)
        if curves:
            length = max(len(c) for c in curves)
            # A finished search stays where it ended: pad each curve with its last distance.
            padded = np.array([c + [c[-1]] * (length - len(c)) for c in curves])
            ax.plot(
                range(1, length + 1),
                np.median(padded, axis=0),
                color="C3",
                linewidth=2.0,
                label="median",
            )
            ax.legend(fontsize=8)
        ax.set_title(f"{strategy} (clean targets)")
        ax.set_xlabel("iteration (1 = start view)")
        ax.set_ylabel("angle to the true pose (°)")
    fig.tight_layout()
    path = out / "distance.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written
