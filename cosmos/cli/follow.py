"""Following a search as it runs: each iteration, the result, the plots (``cosmos search`` and
``cosmos demo``)."""

from __future__ import annotations

from pathlib import Path

from services.common.contracts.free import FreeAnswer, FreePose
from services.common.contracts.search import Iteration, Search
from services.controller.client import (
    ControllerClient,
)

__all__ = ["follow"]


def _triple(values: tuple[float, ...], digits: int = 2) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def _print_free_iteration(it: Iteration) -> None:
    camera = it.camera
    where = f"camera at ({_triple(camera.position)})" if camera is not None else ""
    score = f"match {it.match.score:.2f}" if it.match is not None else ""
    agrees = it.agrees if it.agrees is not None else it.done  # an older record: by ``done``
    print(
        f"  [{it.index + 1:>2}] {where} {len(it.detections)} objects  "
        f"{it.timings.total_ms:6.0f} ms  {score}  {'agrees' if agrees else 'disagrees'}",
        flush=True,
    )


def _print_pose(pose: FreePose, indent: str = "  ") -> None:
    k = pose.intrinsics
    lens = f", distortion {_triple(tuple(k.distortion.coefficients()), 4)}" if k.distortion else ""
    sigma = (
        f"; 1σ {pose.position_sigma:.3g} units, {pose.rotation_sigma_deg:.2g}°"
        if pose.position_sigma is not None and pose.rotation_sigma_deg is not None
        else ""
    )
    print(f"{indent}position ({_triple(pose.position)}) scene units")
    print(
        f"{indent}yaw/pitch/roll ({_triple(pose.yaw_pitch_roll_deg, 1)})°, quaternion wxyz "
        f"({_triple(pose.quaternion_wxyz, 4)})"
    )
    print(
        f"{indent}intrinsics {k.source}: fov {k.fov_deg:.2f}°, fx {k.fx_px:.1f} fy {k.fy_px:.1f} "
        f"cx {k.cx_px:.1f} cy {k.cy_px:.1f} px{lens}"
    )
    pairs = ", ".join(f"#{c.detection}={c.object}" for c in pose.correspondences)
    print(
        f"{indent}{len(pose.correspondences)} objects paired ({pairs}), residual "
        f"{pose.residual_px:.2f} px{sigma}"
    )


def _print_free(free: FreeAnswer, confidence: float, confirmed: bool) -> None:
    status = free.status if confirmed else f"{free.status}, NOT CONFIRMED"
    g = free.nearest_grid
    print(f"{status}: confidence {confidence:.2f}, {free.renders} render(s)")
    _print_pose(free.pose)
    print(
        f"  nearest grid pose: lat {g.index.lat} lon {g.index.lon} (θ {g.theta_deg:.1f}° "
        f"φ {g.phi_deg:.1f}°)"
    )
    for n, alternative in enumerate(free.alternatives, 1):
        print(f"  alternative {n}:")
        _print_pose(alternative, "    ")


def _print_iteration(it: Iteration) -> None:
    if it.camera is not None:
        _print_free_iteration(it)
        return
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
    free = final.result.free if final.result is not None else None
    if final.result is not None and free is not None:
        _print_free(free, final.result.confidence, final.result.confirmed)
        print(final.result.reason)
    elif final.result is not None:
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
