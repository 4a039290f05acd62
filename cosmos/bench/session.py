"""What every mode of ``cosmos bench`` shares: its configuration, the services it runs against
(a local stack on free ports, or ``--url``), searching every target, and writing a report.

The modes themselves are :mod:`cosmos.bench.command` and :mod:`cosmos.bench.random_run`.
"""

from __future__ import annotations

import json
import os
import shlex
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Final, Literal

import httpx

from cosmos.bench.results_md import write_results_md
from cosmos.bench.runner import (
    BenchTarget,
    SearchRecord,
    local_stack,
    make_targets,
    run_searches,
    with_starts,
)
from cosmos.bench.variants import Variant
from services.common.auth import bearer, token_from_environment
from services.common.catalog import SceneCatalog
from services.common.contracts.optimize import StrategyName
from services.common.geometry.scene import LoadedScene

__all__ = [
    "START_MODES",
    "BenchConfig",
    "Endpoints",
    "load_at_end",
    "open_endpoints",
    "progress_printer",
    "say",
    "search_all",
    "services_info",
    "write_report",
]


StartMode = Literal["given", "predicted"]
START_MODES: tuple[StartMode, ...] = ("given", "predicted")


@dataclass(frozen=True)
class BenchConfig:
    """Everything ``cosmos bench`` was asked to do."""

    n: int = 60
    scenes: tuple[str, ...] = ("demo", "garden")
    strategies: tuple[StrategyName, ...] = ("simple", "paper", "reprojection")
    variants: tuple[Variant, ...] = ("clean", "jpeg", "noise", "offgrid")
    starts: tuple[StartMode, ...] = ("given", "predicted")
    """How searches start: ``given`` the target's drawn start (the paper's protocol), and
    ``predicted`` none (the controller predicts it from the target)."""
    seed: int = 2024
    out: Path = Path("docs/results")
    results_md: Path | None = Path("docs/RESULTS.md")
    url: str | None = None
    api_key: str | None = field(default=None, repr=False)
    """With ``url``: the key sent to that controller (a local stack has its own)."""
    renderer_url: str | None = None
    spp: int | None = None
    width: int | None = None
    concurrency: int = 1
    max_iterations: int = 60
    profile: bool = False
    profile_n: int = 20
    sweep: tuple[int, ...] = ()
    sweep_widths: tuple[int, ...] = ()
    sweep_poses: int = 24
    throughput: bool = False
    throughput_searches: int = 20
    renderers: int = 2
    detectors: int = 2
    max_concurrent_searches: int | None = None
    random_scenes: int = 0
    onboard: Literal["none", "tiny", "default"] | None = None
    """With ``random_scenes``: the onboarding preset of the scenes' own models; unset, the
    hemisphere bench onboards (``default``) and the free bench does not (``none``)."""
    scenes_out: Path | None = None
    free: bool = False
    """Free-camera targets (``cosmos bench --free``, :mod:`cosmos.bench.free_bench`)."""
    target_width: int | None = None
    """With ``free``: the targets' film width; None: the scene camera's."""
    target_aspect: tuple[int, int] | None = None
    """With ``free``: the targets' film shape ``(w, h)``; None: the scene camera's."""
    roll_limit: float | None = None
    """With ``free``: the targets' roll within ± this (degrees); None: issue 23's ±25°
    (:data:`~cosmos.bench.free_targets.draw.ROLL_LIMIT_DEG`)."""
    fov_range: tuple[float, float] | None = None
    """With ``free``: the targets' fov as factors of the scene camera's; None: issue 23's
    ±30 % (:data:`~cosmos.bench.free_targets.draw.FOV_RANGE`)."""
    chunk_minutes: float | None = None
    """With ``free``: stop starting searches after this long; the same command resumes."""
    regenerate: bool = False
    verbose: bool = False
    notes: tuple[str, ...] = ()
    command: str = field(default_factory=lambda: "cosmos " + shlex.join(sys.argv[1:]))


def say(message: str) -> None:
    print(message, flush=True)  # noqa: T201 - the command's own output


@dataclass(frozen=True)
class Endpoints:
    controller: str
    renderer: str
    api_key: str | None = field(default=None, repr=False)
    """The key sent to the controller (the local stack's, or ``--url``'s)."""
    renderers: tuple[str, ...] = ()
    detectors: tuple[str, ...] = ()
    scene_dirs: tuple[Path, ...] = ()
    """Scene folders the local stack reads besides the built-in ones (and this process's
    ``COSMOS_SCENES_DIR``)."""
    altered_dir: Path | None = None
    """Where ``photo`` and ``changed`` targets' scene copies go (a local stack reads it)."""
    service_token: str | None = field(default=None, repr=False)
    """What the renderers and detectors ask of their callers (the stack's service token)."""

    @cached_property
    def _catalog(self) -> SceneCatalog:
        from services.renderer.settings import RendererSettings

        # Not the copies' folder: it grows with every target and no copy is copied again.
        dirs = [d for d in self.scene_dirs if d != self.altered_dir]
        return SceneCatalog([*dirs, *RendererSettings().scene_directories()])

    def scene_of(self, scene_id: str) -> LoadedScene:
        """The scene ``scene_id`` as the local stack's renderer reads it."""
        return self._catalog.get(scene_id)

    def warm(self, scenes: Sequence[str]) -> None:
        """Render every scene on every renderer and detect it on every detector once, so that
        no replica pays a first-call cost (scene load, kernel compile) inside a measurement."""
        from services.common.contracts.render import RenderRequest
        from services.common.geometry.pose import PoseQuery
        from services.renderer.client import RendererClient

        for url in self.renderers:
            with RendererClient(url, token=self.service_token) as renderer:
                for scene in scenes:
                    request = RenderRequest(scene=scene, pose=PoseQuery(lat=0, lon=0))
                    png = renderer.render_png(request)
                    for detector in self.detectors:
                        httpx.post(
                            f"{detector}/detect",
                            files={"image": ("warm.png", png, "image/png")},
                            headers=bearer(self.service_token),
                            timeout=60.0,
                        ).raise_for_status()


@contextmanager
def open_endpoints(
    config: BenchConfig,
    *,
    spp: int | None,
    width: int | None,
    renderers: int = 1,
    detectors: int = 1,
    scene_dirs: Sequence[Path] = (),
) -> Iterator[Endpoints]:
    if config.url is not None:
        if config.renderer_url is None:
            raise ValueError("--url needs --renderer-url too (the targets are rendered there)")
        yield Endpoints(
            config.url.rstrip("/"),
            config.renderer_url.rstrip("/"),
            config.api_key,
            service_token=token_from_environment(),  # the renderer's, as cosmos up was given
        )
        return
    with tempfile.TemporaryDirectory(prefix="cosmos-bench-") as tmp:
        started = time.perf_counter()
        altered = Path(tmp) / "altered"
        altered.mkdir()
        dirs = (*scene_dirs, altered)
        with local_stack(
            Path(tmp),
            renderers=renderers,
            detectors=detectors,
            render_spp=spp,
            render_width=width,
            max_concurrent_searches=config.max_concurrent_searches,
            scene_dirs=dirs,
        ) as stack:
            say(
                f"stack up in {time.perf_counter() - started:.1f} s: controller "
                f"{stack.controller}, {renderers} renderer(s), {detectors} detector(s)"
                + (f", search views at {spp} spp" if spp is not None else "")
                + (f", {width} px wide" if width is not None else "")
            )
            yield Endpoints(
                stack.controller,
                stack.renderers[0],
                stack.api_key,
                stack.renderers,
                stack.detectors,
                scene_dirs=tuple(dirs),
                altered_dir=altered,
                service_token=stack.service_token,
            )


def services_info(endpoints: Endpoints, spp: int | None, width: int | None) -> dict[str, Any]:
    """What the running services say about themselves (variant, model), for the report."""
    info: dict[str, Any] = {}
    with httpx.Client(timeout=10.0) as http:
        try:
            renderer = http.get(f"{endpoints.renderer}/health").json()
            info["mitsuba_variant"] = renderer.get("variant")
            # The controller's /health names replicas, never addresses: ask a known detector.
            detector = endpoints.detectors[0]
            model = http.get(f"{detector}/model", headers=bearer(endpoints.service_token)).json()
            info["detector_model"] = f"{model['name']} (sha256 {model['sha256'][:12]})"
            info["detector_input"] = "×".join(str(v) for v in model["input_size"])
        except (httpx.HTTPError, KeyError, IndexError, ValueError) as exc:
            info["services"] = f"not fully reported ({exc})"
    from services.controller.settings import ControllerSettings

    defaults = ControllerSettings()  # what a local stack's controller reads too
    default_spp = (
        defaults.controller_view_spp
        if defaults.controller_view_spp is not None
        else "renderer default"
    )
    default_width = (
        defaults.controller_view_width
        if defaults.controller_view_width is not None
        else "scene's own"
    )
    info["search_view_spp"] = spp if spp is not None else f"{default_spp} (controller default)"
    info["search_view_width"] = (
        width if width is not None else f"{default_width} (controller default)"
    )
    return info


def load_at_end() -> dict[str, float]:
    """The 1-minute load average as the run ends (other work on the machine skews timings)."""
    return (
        {"load_average_1m_at_end": round(os.getloadavg()[0], 2)}
        if hasattr(os, "getloadavg")
        else {}
    )


def progress_printer(total: int, verbose: bool) -> Any:
    started = time.perf_counter()
    step = max(1, total // 20)

    def report(done: int, record: SearchRecord) -> None:
        if verbose or record.status == "error":
            mark = "ok " if record.success else "MISS"
            say(
                f"  [{done:>4}/{total}] {mark} {record.scene} {record.variant:<8} "
                f"{record.strategy:<12} #{record.number:<3} {record.renders:>2} renders "
                f"{record.wall_ms:7.0f} ms {record.status}"
                + (f": {record.error}" if record.error else "")
            )
        elif done % step == 0 or done == total:
            elapsed = time.perf_counter() - started
            say(
                f"  {done}/{total} searches, {elapsed:.0f} s, "
                f"~{elapsed / done * (total - done):.0f} s left"
            )

    return report


def search_all(
    config: BenchConfig,
    endpoints: Endpoints,
    variants: Sequence[Variant],
    strategies: Sequence[StrategyName],
) -> tuple[list[BenchTarget], list[SearchRecord]]:
    targets = make_targets(
        endpoints.renderer,
        config.scenes,
        variants,
        config.n,
        config.seed,
        progress=say,
        scene_of=endpoints.scene_of,
        altered_dir=endpoints.altered_dir,
        token=endpoints.service_token,
    )
    endpoints.warm(config.scenes)
    firsts = {t.scene: t for t in reversed(targets)}
    run_searches(  # untimed: every stage's first call per scene and strategy
        endpoints.controller,
        [(t, s) for t in firsts.values() for s in strategies],
        max_iterations=config.max_iterations,
        api_key=endpoints.api_key,
    )
    jobs = [(t, s) for t in with_starts(targets, config.starts) for s in strategies]
    say(f"{len(jobs)} searches, {config.concurrency} in flight")
    records = run_searches(
        endpoints.controller,
        jobs,
        concurrency=config.concurrency,
        max_iterations=config.max_iterations,
        progress=progress_printer(len(jobs), config.verbose),
        api_key=endpoints.api_key,
    )
    return targets, records


DECIMALS: Final = 4
"""A report's floats are written to this many decimals (0.1 µs, 0.0001 scene units)…"""
FINE_DECIMALS: Final = {"quaternion_wxyz": 8}
"""…but these fields to more: a unit quaternion's components to 4 decimals turn a rotation by
up to ~0.01°, a fifth of the free bench's median rotation error, and its real-stack test
compared an error recomputed from the raw answer with the record's to 0.01° (once 0.0104° off)."""


def _rounded(value: Any, decimals: int = DECIMALS) -> Any:
    if isinstance(value, float):
        return round(value, decimals)
    if isinstance(value, dict):
        return {k: _rounded(v, FINE_DECIMALS.get(k, decimals)) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_rounded(v, decimals) for v in value]
    return value


def write_report(config: BenchConfig, name: str, report: dict[str, Any]) -> None:
    config.out.mkdir(parents=True, exist_ok=True)
    path = config.out / name
    # Compact, floats rounded (DECIMALS): a 1440-search report stays ~1.5 MB.
    path.write_text(json.dumps(_rounded(report), separators=(",", ":"), default=str) + "\n")
    say(f"wrote {path}")
    if config.results_md is not None:
        write_results_md(config.results_md, config.out)
        say(f"wrote {config.results_md}")
