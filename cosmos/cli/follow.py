"""Following a search as it runs: each iteration, the result, the plots (``cosmos search`` and
``cosmos demo``)."""

from __future__ import annotations

from pathlib import Path

from services.common.contracts.search import Iteration, Search
from services.controller.client import (
    ControllerClient,
)

__all__ = ["follow"]


def _print_iteration(it: Iteration) -> None:
    pose = it.pose
    est = (
        f"estimate θ {it.estimate.theta_deg:5.1f}° φ {it.estimate.phi_deg:5.1f}°"
        if it.estimate
        else ""
    )
    print(
        f"  [{it.index + 1:>2}] lat {pose.index.lat:>2} lon {pose.index.lon:>2} "
        f"(θ {pose.theta_deg:5.1f}° φ {pose.phi_deg:5.1f}°) {len(it.detections)} objects  "
        f"{it.timings.total_ms:6.0f} ms  {est}",
        flush=True,
    )


def follow(client: ControllerClient, search: Search, out: Path | None) -> Search:
    """Print each iteration as it happens, then the result; save the plots into ``out``."""
    final = search
    for item in client.follow(search.id):
        if isinstance(item, Iteration):
            _print_iteration(item)
        else:
            final = item
    if final.result is not None:
        r = final.result
        status = final.status if r.confirmed else f"{final.status}, NOT CONFIRMED"
        print(
            f"{status}: lat {r.pose.index.lat} lon {r.pose.index.lon} "
            f"(θ {r.pose.theta_deg:.1f}° φ {r.pose.phi_deg:.1f}°), refined θ "
            f"{r.refined_pose.theta_deg:.2f}° φ {r.refined_pose.phi_deg:.2f}°, confidence "
            f"{r.confidence:.2f}, {r.renders} renders"
        )
        if not r.confirmed:  # the best visited pose, not a match: say why
            print(r.reason)
    if final.error is not None:
        print(f"{final.status}: {final.error.detail}")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for name in ("trajectory.png", "distance.png"):
            path = out / f"search-{final.id[:8]}-{name}"
            path.write_bytes(client.plot(final.id, name))
            print(f"wrote {path}")
    return final
