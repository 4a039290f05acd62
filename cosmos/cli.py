"""The ``cosmos`` command: render views, list scenes, run the demo.

* ``cosmos scenes [--url URL]``: the scenes (local files, or a running renderer);
* ``cosmos scenes add PATH`` (or ``cosmos onboard PATH``): train, measure and install the scene's
  own detector beside its file (:mod:`training.onboard`; needs the ``train`` extra);
* ``cosmos render --scene demo --theta 40 --phi 120 -o target.png``: one view, rendered in this
  process or by a renderer at ``--url``; ``--annotations FILE`` also writes its ground truth;
* ``cosmos up``: the four services as local processes, each started again if it exits (Ctrl-C
  or SIGTERM stops them all), and the local API key, printed and kept beside the controller's
  database (``data/api-key``);
* ``cosmos search target.png --scene demo``: submit a search (waiting out a controller that
  says when to come back, for up to ``--retry-for`` seconds), follow it, save its plots;
* ``cosmos keys create [--admin] [--name N]``, ``cosmos keys list``, ``cosmos keys revoke ID``:
  the controller's API keys, in its database (``COSMOS_CONTROLLER_DATABASE_URL``);
* ``cosmos demo``: the whole thing end to end on the demo scene: starts the stack on free ports,
  renders a target from a random grid pose, searches for it, prints the true and found poses;
* ``cosmos bench``: the paper's evaluation through the real services (:mod:`cosmos.bench`).

The commands that call a running controller (``search``, ``bench --url``) send the key in
``COSMOS_API_KEY``, else the one ``cosmos up`` keeps beside the controller's database; ``demo``
and ``bench`` without ``--url`` start their own stack, with its own key.
"""

from __future__ import annotations

import argparse
import random
import shlex
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from cosmos.launch import ROOT
from cosmos.stack import local_stack, plan_stack, running_stack
from services.common.auth import TOKEN_VARIABLE, token_from_environment
from services.common.catalog import BUILTIN_SCENES_DIR, SceneCatalog
from services.common.contracts.render import RenderAnnotations, RenderRequest
from services.common.contracts.search import Iteration, Search
from services.common.errors import ServiceError
from services.common.geometry.pose import PoseQuery
from services.controller.client import (
    DEFAULT_RETRY_BUDGET_S,
    RETRYABLE_STATUSES,
    ControllerClient,
    ControllerError,
)
from services.controller.keys import KeyStore, client_key, key_file, local_key, rooted
from services.renderer.client import RendererClient, RendererError
from services.renderer.settings import RendererSettings

__all__ = ["main"]


def _pose_query(args: argparse.Namespace) -> PoseQuery:
    if args.lat is not None or args.lon is not None:
        return PoseQuery(lat=args.lat, lon=args.lon)
    return PoseQuery(theta_deg=args.theta, phi_deg=args.phi)


def _cmd_scenes(args: argparse.Namespace) -> int:
    if args.url:
        with RendererClient(args.url, token=token_from_environment()) as client:
            for summary in client.scenes():
                print(
                    f"{summary.id:<16} {summary.objects:>3} objects  {summary.grid_size:>5} poses"
                )
        return 0
    catalog = SceneCatalog(RendererSettings().scene_directories())
    for scene_id in catalog.ids():
        scene = catalog.get(scene_id)
        print(
            f"{scene_id:<16} {len(scene.spec.objects):>3} objects  "
            f"{scene.spec.search.grid().size:>5} poses  {scene.path}"
        )
    for scene_id, error in catalog.invalid().items():
        print(f"{scene_id:<16} INVALID: {error}")
    return 0


class _ProgressBar:
    """One ``\\r``-rewritten line: stage, a bar, percent, elapsed and estimated time left (a
    plain line per stage when the output is not a terminal)."""

    WIDTH = 28

    def __init__(self) -> None:
        self._started = time.monotonic()
        self._tty = sys.stderr.isatty()
        self._stage = ""
        self._shown = -1

    def __call__(self, stage: str, fraction: float) -> None:
        elapsed = time.monotonic() - self._started
        if not self._tty:
            if stage != self._stage:
                print(f"{stage}...", file=sys.stderr, flush=True)
            self._stage = stage
            return
        percent = int(100 * fraction)
        if percent == self._shown and stage == self._stage:
            return
        self._stage, self._shown = stage, percent
        filled = int(self.WIDTH * fraction)
        eta = f"{elapsed / fraction - elapsed:4.0f} s left" if fraction > 0.02 else "   ..."
        line = (
            f"\r{stage:<9} [{'#' * filled}{'.' * (self.WIDTH - filled)}] {percent:3d}%  "
            f"{elapsed:4.0f} s, {eta}"
        )
        print(line, end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._tty and self._shown >= 0:
            print(file=sys.stderr, flush=True)


def _cmd_onboard(args: argparse.Namespace) -> int:
    from services.common.geometry.scene import SceneFileError

    try:
        from training.onboard import OnboardOptions, TorchMissingError, onboard_scene
    except ImportError as exc:  # a wheel without the training package
        print(
            f"cosmos: onboarding needs the repository's training package ({exc})", file=sys.stderr
        )
        return 1
    path = Path(args.path)
    preset = OnboardOptions.tiny() if args.tiny else OnboardOptions()
    overrides = {
        "train_images": args.images,
        "val_images": args.val_images,
        "epochs": args.epochs,
        "max_minutes": args.max_minutes,
        "seed": args.seed,
    }
    options = replace(preset, **{k: v for k, v in overrides.items() if v is not None})
    work = Path(args.work) if args.work else None
    bar = _ProgressBar()
    try:
        report = onboard_scene(path, options, work_dir=work, progress=bar)
    except SceneFileError as exc:
        bar.close()
        print(f"cosmos: invalid scene: {exc}", file=sys.stderr)
        return 2
    except TorchMissingError as exc:
        print(f"cosmos: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        bar.close()
        print(
            "stopped; nothing was installed. Run the same command again to resume "
            "(finished renders and training epochs are kept).",
            file=sys.stderr,
        )
        return 130
    bar.close()
    m = report.minutes
    print(f"model of scene {report.scene}: {report.model_path}")
    print(f"classes: {', '.join(report.classes)}")
    print(
        f"held-out renders ({report.val_images} images): precision {report.precision:.3f}, "
        f"recall {report.recall:.3f}, mAP50 {report.map50:.3f}"
    )
    print(
        f"{report.images} training images, {report.epochs} epochs; minutes: render "
        f"{m.render:.1f}, train {m.train:.1f}, evaluate {m.eval:.1f}, total {m.total:.1f}"
    )
    print("a running detector picks the model up by itself (it hot-reloads; nothing to restart)")
    folder = path.resolve().parent
    known = [d.resolve() for d in RendererSettings().scene_directories()]
    if folder not in known:
        print(
            f"the scene's folder is not a scenes folder of the catalog; for cosmos up, set "
            f"COSMOS_SCENES_DIR={shlex.quote(str(folder))}"
        )
    return 0


def _render_local(request: RenderRequest) -> tuple[bytes, RenderAnnotations | None, str]:
    from services.renderer.engine import RenderEngine
    from services.renderer.imaging import encode_png
    from services.renderer.view import resolve_view

    settings = RendererSettings()
    view = resolve_view(SceneCatalog(settings.scene_directories()), settings, request)
    engine = RenderEngine(settings.renderer_mitsuba_variant)
    engine.start()
    try:
        image = engine.render(view.scene, view.pose, view.width, view.height, view.spp, view.seed)
        ann = engine.annotate(view.scene, view.pose, view.width, view.height, view.grid_index)
        return encode_png(image.rgb), ann, engine.variant
    finally:
        engine.close()


def _cmd_render(args: argparse.Namespace) -> int:
    request = RenderRequest(
        scene=args.scene,
        pose=_pose_query(args),
        width=args.width,
        height=args.height,
        spp=args.spp,
        seed=args.seed,
    )
    if args.url:
        with RendererClient(args.url, token=token_from_environment()) as client:
            png = client.render_png(request)
            ann = client.annotations(request) if args.annotations else None
        where = args.url
    else:
        png, ann, where = _render_local(request)
    Path(args.output).write_bytes(png)
    print(f"wrote {args.output} ({len(png)} bytes, {where})")
    if args.annotations and ann is not None:
        Path(args.annotations).write_text(ann.model_dump_json(indent=2))
        print(f"wrote {args.annotations}")
    return 0


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


def _follow(client: ControllerClient, search: Search, out: Path | None) -> Search:
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


def _database_url(given: str | None = None) -> str:
    """The controller database a local command means: ``given``, else the controller's own
    setting (``COSMOS_CONTROLLER_DATABASE_URL`` or its default); a relative path is taken from
    the repository root, where ``cosmos up`` runs the services."""
    from services.controller.settings import ControllerSettings

    return rooted(given or ControllerSettings().controller_database_url, ROOT)


def _client_key() -> str | None:
    """``COSMOS_API_KEY``, else the local key ``cosmos up`` keeps (None: none found)."""
    return client_key(_database_url())


def _waiting(refusal: ControllerError, wait_s: float) -> None:
    """Tell the user why the submission waits (a quota, a busy or degraded controller)."""
    _say(
        f"the controller cannot take the search yet ({refusal.status}: {refusal.detail}); "
        f"asking again in {wait_s:g} s"
    )


def _not_taken(refusal: ControllerError, budget_s: float) -> str:
    """The sentence for a submission the controller refused until the retry budget ran out."""
    waited = f" after waiting {refusal.waited_s:g} s" if refusal.waited_s else ""
    return (
        f"the controller did not take the search{waited} ({refusal.status}: {refusal.detail}); "
        f"it asks to try again in {refusal.retry_after_s:g} s, beyond --retry-for "
        f"{budget_s:g} s: try again later, or give --retry-for more seconds"
    )


def _cmd_search(args: argparse.Namespace) -> int:
    image = Path(args.image).read_bytes()
    with ControllerClient(args.url, api_key=_client_key()) as client:
        try:
            search = client.submit(
                image,
                args.scene,
                retry_budget_s=args.retry_for,
                on_wait=_waiting,
                strategy=args.strategy,
                start_theta_deg=args.start_theta,
                start_phi_deg=args.start_phi,
                seed=args.seed,
                max_iterations=args.max_iterations,
            )
        except ControllerError as exc:
            if exc.status not in RETRYABLE_STATUSES or exc.retry_after_s is None:
                raise
            print(f"cosmos: {_not_taken(exc, args.retry_for)}", file=sys.stderr)
            return 1
        print(
            f"search {search.id} queued: {search.strategy} on {search.scene} from lat "
            f"{search.start.index.lat} lon {search.start.index.lon}"
        )
        final = _follow(client, search, Path(args.out))
    return 0 if final.status == "succeeded" else 3


def _say(message: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} cosmos: {message}", file=sys.stderr, flush=True)


def _cmd_up(args: argparse.Namespace) -> int:
    from cosmos.environment import report_unknown_variables

    report_unknown_variables()  # each service warns too, but into its log file
    database_url = _database_url(args.database_url)
    try:
        api_key: str | None = local_key(database_url)
        where = f"kept in {key_file(database_url)}, which cosmos search reads"
    except ValueError as exc:  # an in-memory database: no other process can add a key
        api_key, where = None, str(exc)
    plan = plan_stack(
        host=args.host,
        controller_port=args.port,
        renderer_port=args.port + 1,
        detector_port=args.port + 2,
        optimizer_port=args.port + 3,
        renderers=args.renderers,
        detectors=args.detectors,
        database_url=database_url,
        service_token=token_from_environment(),  # else one for this run
    )
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    with running_stack(
        plan, Path(args.logs), host=args.host, api_key=api_key, supervise=True, say=_say
    ) as stack:
        print(f"controller  {stack.controller}")
        print(f"page        {stack.controller}/ (open it in a browser; it asks for the key once)")
        print(f"API key     {stack.api_key or 'none'} (admin; {where})")
        for name, urls in (
            ("renderer", stack.renderers),
            ("detector", stack.detectors),
            ("optimizer", stack.optimizers),
        ):
            print(f"{name:<11} {', '.join(urls)}")
        if token_from_environment() is None:
            print(
                "the stages serve only the controller (a new service token for this run; set "
                f"{TOKEN_VARIABLE} before cosmos up to call them yourself)"
            )
        print(
            f"logs in {args.logs}; a service that exits is started again; Ctrl-C stops everything",
            flush=True,
        )
        while not stop.wait(1.0):
            pass
    print("stopped")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    """Start the stack on free ports, render a target from a random grid pose, search for it."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = SceneCatalog([BUILTIN_SCENES_DIR]).get("demo")
    grid = scene.spec.search.grid()
    rng = random.Random(args.seed)
    index = grid.unflat(rng.randrange(grid.size))
    pose = grid.pose(index)
    print(f"demo scene: {len(scene.spec.objects)} objects, {grid.size} grid poses")
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        with local_stack(Path(tmp)) as stack:
            print(
                f"stack up in {time.perf_counter() - started:.1f} s (controller {stack.controller})"
            )
            with RendererClient(stack.renderers[0], token=stack.service_token) as renderer:
                target = renderer.render_png(
                    RenderRequest(scene="demo", pose=PoseQuery(lat=index.lat, lon=index.lon))
                )
            (out / "demo-target.png").write_bytes(target)
            print(
                f"target rendered at lat {index.lat}, lon {index.lon} "
                f"(θ {pose.theta_deg:.1f}°, φ {pose.phi_deg:.1f}°): {out / 'demo-target.png'}"
            )
            with ControllerClient(stack.controller, api_key=stack.api_key) as client:
                search = client.submit(target, "demo", seed=rng.randrange(2**31))
                print(
                    f"searching with {search.strategy} from lat {search.start.index.lat}, "
                    f"lon {search.start.index.lon}"
                )
                final = _follow(client, search, out)
    found = final.result
    print(
        f"true pose:  lat {index.lat:>2}, lon {index.lon:>2} "
        f"(θ {pose.theta_deg:.1f}°, φ {pose.phi_deg:.1f}°)"
    )
    if found is not None:
        print(
            f"found pose: lat {found.pose.index.lat:>2}, lon {found.pose.index.lon:>2} "
            f"(θ {found.pose.theta_deg:.1f}°, φ {found.pose.phi_deg:.1f}°) "
            f"after {found.renders} renders"
        )
    print(f"total {time.perf_counter() - started:.1f} s")
    ok = found is not None and found.pose.index == index
    print("the search found the target's grid pose" if ok else "the search did NOT find the target")
    return 0 if ok else 3


@contextmanager
def _key_store(args: argparse.Namespace) -> Iterator[tuple[KeyStore, str]]:
    database_url = _database_url(args.database_url)
    keys = KeyStore(database_url)
    try:
        yield keys, database_url
    finally:
        keys.close()


def _cmd_keys_create(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, database_url):
        record, key = keys.create(args.name, admin=args.admin)
    kind = "admin key" if record.admin else "key"
    print(
        f"{kind} {record.id} ({record.name}) created in {database_url}; it is shown only now, "
        "keep it (clients read COSMOS_API_KEY):",
        file=sys.stderr,
    )
    print(key)  # alone on stdout: KEY=$(cosmos keys create)
    return 0


def _cmd_keys_list(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, _):
        records = keys.all()
    print(f"{'id':<12}  {'name':<20}  {'kind':<6}  {'created (UTC)':<19}  revoked (UTC)")
    for record in records:
        kind = "admin" if record.admin else "tenant"
        created = f"{record.created_at:%Y-%m-%d %H:%M:%S}"
        revoked = f"{record.revoked_at:%Y-%m-%d %H:%M:%S}" if record.revoked_at else ""
        print(f"{record.id:<12}  {record.name:<20}  {kind:<6}  {created:<19}  {revoked}")
    return 0


def _cmd_keys_revoke(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, database_url):
        try:
            record = keys.revoke(args.id)
        except KeyError:
            raise ValueError(f"no key {args.id!r} in {database_url} (cosmos keys list)") from None
    print(f"revoked key {record.id} ({record.name}): it is refused from now on")
    return 0


def _csv(value: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in value.split(",") if part.strip())


def _cmd_bench(args: argparse.Namespace) -> int:
    from cosmos.bench import VARIANTS, BenchConfig, run

    # Random scenes: the project's strategy on every variant; otherwise the paper's comparison.
    random = args.random_scenes > 0
    strategies = _csv(
        args.strategies or ("reprojection" if random else "simple,paper,reprojection")
    )
    variants = _csv(args.variants or (",".join(VARIANTS) if random else "clean,jpeg,noise,offgrid"))
    for name, given, allowed in (
        ("strategy", strategies, ("simple", "paper", "reprojection")),
        ("variant", variants, VARIANTS),
    ):
        unknown = [v for v in given if v not in allowed]
        if unknown or not given:
            raise ValueError(f"unknown {name} {unknown or given}; choose from {', '.join(allowed)}")
    config = BenchConfig(
        n=args.n,
        scenes=_csv(args.scenes),
        strategies=strategies,  # type: ignore[arg-type]
        variants=variants,  # type: ignore[arg-type]
        seed=args.seed,
        out=Path(args.out),
        results_md=Path(args.results_md) if args.results_md else None,
        url=args.url,
        api_key=_client_key() if args.url else None,
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
        regenerate=args.regenerate,
        verbose=args.verbose,
        notes=tuple(args.note or ()),
    )
    return run(config)


def _onboard_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the scene file (YAML); its assets lie in its folder")
    parser.add_argument("--work", help="folder for renders and checkpoints (data/onboard/<id>)")
    parser.add_argument("--images", type=int, help="training images to render")
    parser.add_argument("--val-images", type=int, help="held-out images to render")
    parser.add_argument("--epochs", type=int, help="fine-tuning epochs")
    parser.add_argument("--max-minutes", type=float, help="wall-time budget of the whole run")
    parser.add_argument("--seed", type=int, help="seed of the renders (held-out: seed + 1000)")
    parser.add_argument("--tiny", action="store_true", help="a CI-sized run (plumbing only)")
    parser.set_defaults(run=_cmd_onboard)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cosmos", description="COSMOS 3D Search")
    commands = parser.add_subparsers(dest="command", required=True)

    scenes = commands.add_parser("scenes", help="list the scenes, or add one (train its detector)")
    scenes.add_argument("--url", help="ask a running renderer instead of reading the files")
    scenes.set_defaults(run=_cmd_scenes)
    scene_commands = scenes.add_subparsers(dest="scenes_command")
    onboard_help = "train, measure and install a scene's own detector beside its file"
    _onboard_arguments(scene_commands.add_parser("add", help=onboard_help))
    _onboard_arguments(commands.add_parser("onboard", help=onboard_help + " (= scenes add)"))

    render = commands.add_parser("render", help="render one view of a scene to a PNG")
    render.add_argument("--scene", default="demo")
    render.add_argument("--theta", type=float, default=45.0, help="polar angle θ in degrees")
    render.add_argument("--phi", type=float, default=0.0, help="azimuth φ in degrees")
    render.add_argument("--lat", type=int, help="grid ring index (with --lon, instead of angles)")
    render.add_argument("--lon", type=int, help="grid position on the ring")
    render.add_argument("--width", type=int)
    render.add_argument("--height", type=int)
    render.add_argument("--spp", type=int)
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("-o", "--output", default="view.png")
    render.add_argument("--annotations", help="also write the view's ground truth JSON here")
    render.add_argument("--url", help="use a running renderer instead of rendering in-process")
    render.set_defaults(run=_cmd_render)

    demo = commands.add_parser("demo", help="a whole search on the demo scene, end to end")
    demo.add_argument("--out", default="out")
    demo.add_argument("--seed", type=int, help="seed of the random target and start poses")
    demo.set_defaults(run=_cmd_demo)

    up = commands.add_parser("up", help="run the four services as local processes")
    up.add_argument("--host", default="127.0.0.1")
    up.add_argument(
        "--port", type=int, default=8000, help="controller port; stages use the next three"
    )
    up.add_argument("--renderers", type=int, default=1)
    up.add_argument("--detectors", type=int, default=1)
    up.add_argument("--database-url", help="the controller's COSMOS_CONTROLLER_DATABASE_URL")
    up.add_argument("--logs", default="logs", help="folder for the services' logs")
    up.set_defaults(run=_cmd_up)

    keys = commands.add_parser(
        "keys",
        help="create, list and revoke the controller's API keys",
        description="The API keys of the controller whose database is --database-url (default "
        "COSMOS_CONTROLLER_DATABASE_URL's, as the controller reads it). A key sees and cancels "
        "its own searches, within its quotas; an admin key sees everyone's, without quotas.",
    )
    database = argparse.ArgumentParser(add_help=False)
    database.add_argument("--database-url", help="the controller's COSMOS_CONTROLLER_DATABASE_URL")
    key_commands = keys.add_subparsers(dest="keys_command", required=True)
    create = key_commands.add_parser("create", help="a new key, printed once", parents=[database])
    create.add_argument("--name", default="unnamed", help="who or what the key is for")
    create.add_argument("--admin", action="store_true", help="sees every tenant's searches")
    create.set_defaults(run=_cmd_keys_create)
    listing = key_commands.add_parser(
        "list", help="every key (never the keys themselves)", parents=[database]
    )
    listing.set_defaults(run=_cmd_keys_list)
    revoke = key_commands.add_parser("revoke", help="refuse a key from now on", parents=[database])
    revoke.add_argument("id", help="the key's id (cosmos keys list)")
    revoke.set_defaults(run=_cmd_keys_revoke)

    search = commands.add_parser("search", help="search for where an image was taken")
    search.add_argument("image", help="the target image (PNG or JPEG)")
    search.add_argument("--scene", required=True)
    search.add_argument("--url", default="http://127.0.0.1:8000", help="the controller")
    search.add_argument("--strategy", choices=["reprojection", "paper", "simple"])
    search.add_argument("--start-theta", type=float)
    search.add_argument("--start-phi", type=float)
    search.add_argument("--seed", type=int)
    search.add_argument("--max-iterations", type=int)
    search.add_argument("--out", default="out", help="folder for the trajectory plots")
    search.add_argument(
        "--retry-for",
        type=float,
        default=DEFAULT_RETRY_BUDGET_S,
        metavar="SECONDS",
        help="wait out a controller that answers 429 or 503 with Retry-After for up to this "
        "many seconds in all (0: give up at once)",
    )
    search.set_defaults(run=_cmd_search)

    bench = commands.add_parser(
        "bench",
        help="the paper's evaluation: many seeded searches through the real services",
        description="Runs N seeded searches per scene, strategy and target variant against a "
        "local stack started on free ports (or --url), prints the tables and writes the JSON "
        "report, the plots and docs/RESULTS.md.",
    )
    bench.add_argument("--n", type=int, default=60, help="targets per scene and variant")
    bench.add_argument("--scenes", default="demo,garden", help="comma-separated scene ids")
    bench.add_argument(
        "--strategies", help="default simple,paper,reprojection (reprojection with --random-scenes)"
    )
    bench.add_argument(
        "--variants",
        help="of clean,jpeg,noise,offgrid,photo,changed; default the first four (all six with "
        "--random-scenes)",
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
        default="default",
        help="with --random-scenes: the onboarding preset of the per-scene models (none: skip)",
    )
    bench.add_argument(
        "--scenes-out", help="with --random-scenes: keep the scenes and models here (default: temp)"
    )
    bench.add_argument(
        "--regenerate",
        action="store_true",
        help="only rewrite --results-md from the JSON reports in --out (no searches)",
    )
    bench.add_argument("--note", action="append", help="a line for the report (repeatable)")
    bench.add_argument("-v", "--verbose", action="store_true", help="one line per search")
    bench.set_defaults(run=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cosmos``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        status: int = args.run(args)
    except ServiceError as exc:
        print(f"cosmos: {exc.detail}", file=sys.stderr)
        return 2
    except (RendererError, ControllerError, RuntimeError, ValueError, OSError) as exc:
        print(f"cosmos: {exc}", file=sys.stderr)
        return 1
    return status


if __name__ == "__main__":
    sys.exit(main())
