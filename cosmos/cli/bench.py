"""``cosmos bench``: the paper's evaluation through the real services (:mod:`cosmos.bench`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cosmos.cli.common import Commands, client_api_key

__all__ = ["register", "run"]


def _csv(value: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in value.split(",") if part.strip())


class _Listed(argparse.Action):
    """A comma-separated list that a repeated option extends (``--scene demo --scene garden``
    is ``demo,garden``): argparse's plain store kept the last one only, and a bench meant for
    two scenes ran one without a word."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        given = f"_{self.dest}_given"
        before = getattr(namespace, self.dest) if getattr(namespace, given, False) else None
        setattr(namespace, self.dest, f"{before},{values}" if before else str(values))
        setattr(namespace, given, True)


def _aspect(value: str) -> tuple[int, int]:
    """``W:H``: whole numbers, the ratio within 1:4 to 4:1."""
    try:
        w, h = (int(p) for p in value.split(":"))
    except ValueError:
        raise ValueError(f"--target-aspect wants W:H (two whole numbers), not {value!r}") from None
    if w <= 0 or h <= 0 or not 0.25 <= w / h <= 4.0:
        raise ValueError(f"--target-aspect wants W:H between 1:4 and 4:1, not {value!r}")
    return w, h


def _fov_range(value: str) -> tuple[float, float]:
    """``LO,HI``: factors of the scene camera's fov, ``0 < LO <= HI``."""
    parts = _csv(value)
    try:
        low, high = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--fov-range wants LO,HI (two numbers), not {value!r}") from None
    if not 0.0 < low <= high < 10.0:
        raise ValueError(f"--fov-range wants 0 < LO <= HI < 10, not {value!r}")
    return low, high


def run(args: argparse.Namespace) -> int:
    from cosmos.bench import VARIANTS, BenchConfig, run
    from cosmos.bench.free_bench.targets import FREE_BENCH_VARIANTS
    from cosmos.bench.session import START_MODES
    from services.renderer.settings import RendererSettings

    # Random scenes: the project's strategy on every variant; otherwise the paper's comparison.
    random = args.random_scenes > 0
    strategies = _csv(
        args.strategies or ("reprojection" if random else "simple,paper,reprojection")
    )
    default_variants = "clean,jpeg,noise,offgrid"
    if args.free:
        default_variants = ",".join(FREE_BENCH_VARIANTS)
    elif random:
        default_variants = ",".join(VARIANTS)
    variants = _csv(args.variants or default_variants)
    allowed_variants = FREE_BENCH_VARIANTS if args.free else VARIANTS
    starts = _csv(args.starts)
    if args.target_width is not None:
        if not args.free:
            raise ValueError("--target-width draws free targets: add --free")
        most = RendererSettings().renderer_max_side
        if not 16 <= args.target_width <= most:
            raise ValueError(
                f"--target-width must be 16 to {most} pixels (the renderer's longest side, "
                "COSMOS_RENDERER_MAX_SIDE)"
            )
    aspect = _aspect(args.target_aspect) if args.target_aspect is not None else None
    if aspect is not None and not args.free:
        raise ValueError("--target-aspect draws free targets: add --free")
    if args.roll_limit is not None:
        if not args.free:
            raise ValueError("--roll-limit draws free targets: add --free")
        if not 0.0 <= args.roll_limit <= 180.0:  # also refuses nan
            raise ValueError(f"--roll-limit wants 0 to 180 degrees, not {args.roll_limit}")
    fov_range = _fov_range(args.fov_range) if args.fov_range is not None else None
    if fov_range is not None and not args.free:
        raise ValueError("--fov-range draws free targets: add --free")
    for name, given, allowed in (
        ("strategy", strategies, ("simple", "paper", "reprojection")),
        ("variant", variants, allowed_variants),
        ("start", starts, START_MODES),
    ):
        unknown = [v for v in given if v not in allowed]
        if unknown or not given:
            raise ValueError(f"unknown {name} {unknown or given}; choose from {', '.join(allowed)}")
    config = BenchConfig(
        n=args.n,
        scenes=_csv(args.scenes),
        strategies=strategies,  # type: ignore[arg-type]
        variants=variants,  # type: ignore[arg-type]
        starts=starts,  # type: ignore[arg-type]
        seed=args.seed,
        out=Path(args.out),
        results_md=Path(args.results_md) if args.results_md else None,
        url=args.url,
        api_key=client_api_key() if args.url else None,
        renderer_url=args.renderer_url,
        spp=args.spp,
        width=args.width,
        concurrency=args.concurrency,
        max_iterations=args.max_iterations,
        profile=args.profile,
        profile_n=args.profile_n,
        sweep=tuple(int(v) for v in _csv(args.sweep)) if args.sweep else (),
        sweep_widths=tuple(int(v) for v in _csv(args.sweep_widths)) if args.sweep_widths else (),
        sweep_poses=args.sweep_poses,
        throughput=args.throughput,
        throughput_searches=args.throughput_searches,
        renderers=args.renderers,
        detectors=args.detectors,
        max_concurrent_searches=args.max_concurrent_searches,
        random_scenes=args.random_scenes,
        onboard=args.onboard,  # argparse checked the choice
        scenes_out=Path(args.scenes_out) if args.scenes_out else None,
        free=args.free,
        target_width=args.target_width,
        target_aspect=aspect,
        roll_limit=args.roll_limit,
        fov_range=fov_range,
        chunk_minutes=args.chunk_minutes,
        regenerate=args.regenerate,
        verbose=args.verbose,
        notes=tuple(args.note or ()),
    )
    return run(config)


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    bench = commands.add_parser(
        "bench",
        help="the paper's evaluation: many seeded searches through the real services",
        description="Runs N seeded searches per scene, strategy and target variant against a "
        "local stack started on free ports (or --url), prints the tables and writes the JSON "
        "report, the plots and docs/RESULTS.md.",
    )
    bench.add_argument("--n", type=int, default=60, help="targets per scene and variant")
    bench.add_argument(
        "--scenes",
        "--scene",
        action=_Listed,
        default="demo,garden",
        help="comma-separated scene ids (repeatable)",
    )
    bench.add_argument(
        "--strategies",
        action=_Listed,
        help="default simple,paper,reprojection (reprojection with --random-scenes)",
    )
    bench.add_argument(
        "--variants",
        action=_Listed,
        help="of clean,jpeg,noise,offgrid,photo,changed; default the first four (all six with "
        "--random-scenes)",
    )
    bench.add_argument(
        "--starts",
        action=_Listed,
        default="given,predicted",
        help="how searches start: given (the target's random start, the paper's protocol), "
        "predicted (none given: the controller predicts it from the target); default both",
    )
    bench.add_argument("--seed", type=int, default=2024)
    bench.add_argument("--out", default="docs/results", help="folder for the JSON and plots")
    bench.add_argument(
        "--results-md", default="docs/RESULTS.md", help="regenerated from --out ('' skips it)"
    )
    bench.add_argument("--url", help="a running controller instead of a local stack")
    bench.add_argument("--renderer-url", help="with --url: the renderer that renders targets")
    bench.add_argument("--spp", type=int, help="samples per pixel of the searches' views")
    bench.add_argument("--width", type=int, help="film width of the searches' views")
    bench.add_argument("--concurrency", type=int, default=1, help="searches in flight")
    bench.add_argument("--max-iterations", type=int, default=60)
    bench.add_argument(
        "--profile", action="store_true", help="also measure the floor of a search in-process"
    )
    bench.add_argument("--profile-n", type=int, default=20, help="profiled targets per scene")
    bench.add_argument("--sweep", help="render settings by measurement at these spp (e.g. 4,8,16)")
    bench.add_argument("--sweep-widths", help="with --sweep: also these view widths (e.g. 320,160)")
    bench.add_argument("--sweep-poses", type=int, default=24, help="poses per scene (detection)")
    bench.add_argument(
        "--throughput",
        action="store_true",
        help="searches per minute with one replica per stage and with --renderers/--detectors",
    )
    bench.add_argument("--throughput-searches", type=int, default=20)
    bench.add_argument("--renderers", type=int, default=2)
    bench.add_argument("--detectors", type=int, default=2)
    bench.add_argument(
        "--max-concurrent-searches",
        type=int,
        help="the controller's COSMOS_CONTROLLER_MAX_CONCURRENT_SEARCHES",
    )
    bench.add_argument(
        "--random-scenes",
        type=int,
        default=0,
        metavar="N",
        help="search N generated scenes with the general detector, then with each one's own",
    )
    bench.add_argument(
        "--onboard",
        choices=["none", "tiny", "default"],
        default=None,
        help="with --random-scenes: the onboarding preset of the per-scene models (none: skip; "
        "unset: default, or none with --free; with --free an onboarded scene's targets are "
        "searched again with its own model)",
    )
    bench.add_argument(
        "--scenes-out", help="with --random-scenes: keep the scenes and models here (default: temp)"
    )
    bench.add_argument(
        "--free",
        action="store_true",
        help="free-camera targets (any position, orientation, fov) searched with mode=free, "
        "beside a plain solvePnPRansac baseline and the box-only bound; with --random-scenes N "
        "also on N generated scenes",
    )
    bench.add_argument(
        "--target-width",
        type=int,
        metavar="PX",
        help="with --free: draw the targets this wide, at the scene camera's aspect (a drone's "
        "photo is larger than the views; default the scene camera's film)",
    )
    bench.add_argument(
        "--target-aspect",
        metavar="W:H",
        help="with --free: draw the targets on a film of this shape, the fov still across its "
        "width (a drone's photo need not have the scene camera's; default the scene camera's)",
    )
    bench.add_argument(
        "--roll-limit",
        type=float,
        metavar="DEG",
        help="with --free: draw the targets' roll within ±DEG (default 25, issue 23's; 90 "
        "takes in photos held upright)",
    )
    bench.add_argument(
        "--fov-range",
        metavar="LO,HI",
        help="with --free: draw the targets' fov within these factors of the scene camera's "
        "(a drone's lens may be far wider; default 0.7,1.3, issue 23's ±30 %%)",
    )
    bench.add_argument(
        "--chunk-minutes",
        type=float,
        help="with --free: stop starting searches after this long (the same command resumes)",
    )
    bench.add_argument(
        "--regenerate",
        action="store_true",
        help="only rewrite --results-md from the JSON reports in --out (no searches)",
    )
    bench.add_argument("--note", action="append", help="a line for the report (repeatable)")
    bench.add_argument("-v", "--verbose", action="store_true", help="one line per search")
    bench.set_defaults(run=run)
