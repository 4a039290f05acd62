"""``cosmos search target.png --scene demo``: submit a search (waiting out a controller that says
when to come back, for up to ``--retry-for`` seconds), follow it, save its plots. Several images
are searched each in turn, ``--concurrency`` at a time (:mod:`cosmos.cli.batch`); ``--poses
FILE`` writes the answers as a CSV table (:mod:`cosmos.cli.pose_table`).

``--free`` searches for any camera (``mode=free``), optionally with the photo's ``--fov DEG`` or
``--intrinsics FX,FY,CX,CY`` and ``--distortion K1,K2,P1,P2[,K3]`` (the controller checks them);
without them the controller reads the lens from the photo's metadata (a drone's calibration in its
XMP, else the EXIF focal length), unless ``--no-exif``."""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

from cosmos.cli.batch import search_all
from cosmos.cli.common import Commands, accept_negative_lists, client_api_key, say
from cosmos.cli.follow import follow
from cosmos.cli.pose_table import row_of, write_rows
from services.common.contracts.search import Search
from services.controller.client import (
    DEFAULT_RETRY_BUDGET_S,
    RETRYABLE_STATUSES,
    ControllerClient,
    ControllerError,
)

__all__ = ["register", "run"]


def _waiting(refusal: ControllerError, wait_s: float) -> None:
    """Tell the user why the submission waits (a quota, a busy or degraded controller)."""
    say(
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


_FREE_ONLY = ("fov", "intrinsics", "distortion", "attitude")


def _submit(client: ControllerClient, args: argparse.Namespace, image: bytes) -> Search:
    """``image`` submitted with the command's options, refusals that say when to come back
    waited out for up to ``--retry-for`` seconds."""
    return client.submit(
        image,
        args.scene,
        retry_budget_s=args.retry_for,
        on_wait=_waiting,
        strategy=args.strategy,
        start_theta_deg=args.start_theta,
        start_phi_deg=args.start_phi,
        seed=args.seed,
        max_iterations=args.max_iterations,
        mode="free" if args.free else None,
        fov_deg=args.fov,
        intrinsics=args.intrinsics,
        distortion=args.distortion,
        attitude=args.attitude,
        exif="false" if args.no_exif else None,
    )


def _one(client: ControllerClient, args: argparse.Namespace, path: Path) -> Search | None:
    """One photo searched and followed as it runs, its plots saved: the search, None when the
    controller did not take it within ``--retry-for``."""
    try:
        search = _submit(client, args, path.read_bytes())
    except ControllerError as exc:
        if exc.status not in RETRYABLE_STATUSES or exc.retry_after_s is None:
            raise
        print(f"cosmos: {_not_taken(exc, args.retry_for)}", file=sys.stderr)
        return None
    if search.mode == "free":
        print(f"search {search.id} queued: any camera on {search.scene}")
    else:
        print(
            f"search {search.id} queued: {search.strategy} on {search.scene} from lat "
            f"{search.start.index.lat} lon {search.start.index.lon}"
        )
    return follow(client, search, Path(args.out))


def run(args: argparse.Namespace) -> int:
    given = [f"--{name}" for name in _FREE_ONLY if getattr(args, name) is not None]
    given += ["--no-exif"] if args.no_exif else []
    if given and not args.free:
        print(f"cosmos: {', '.join(given)} go with --free", file=sys.stderr)
        return 2
    if args.concurrency < 1:
        print("cosmos: --concurrency must be at least 1", file=sys.stderr)
        return 2
    images = [Path(image) for image in args.image]
    with ControllerClient(args.url, api_key=client_api_key()) as client:
        if len(images) == 1:
            final = _one(client, args, images[0])
            if final is None:
                return 1
            rows = [row_of(str(images[0]), final)]
        else:
            submit = partial(_submit, client, args)
            rows = search_all(client, images, submit, args.concurrency)
    if args.poses is not None:
        write_rows(Path(args.poses), rows)
        print(f"wrote {args.poses}: {len(rows)} photo(s)")
    return 0 if all(row["status"] == "succeeded" for row in rows) else 3


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    search = commands.add_parser("search", help="search for where an image was taken")
    accept_negative_lists(search)
    search.add_argument(
        "image",
        nargs="+",
        help="the target image (PNG or JPEG); several: each searched, a line said for each",
    )
    search.add_argument("--scene", required=True)
    search.add_argument("--url", default="http://127.0.0.1:8000", help="the controller")
    search.add_argument("--strategy", choices=["reprojection", "paper", "simple"])
    search.add_argument("--start-theta", type=float)
    search.add_argument("--start-phi", type=float)
    search.add_argument("--seed", type=int)
    search.add_argument("--max-iterations", type=int)
    search.add_argument(
        "--out", default="out", help="folder for the trajectory plots (one image only)"
    )
    search.add_argument(
        "--poses",
        metavar="FILE",
        help="write the answers as a CSV table, a row per image (its camera, lens, status)",
    )
    search.add_argument(
        "--concurrency",
        type=int,
        default=2,
        metavar="N",
        help="with several images: searches in the controller at a time (default 2)",
    )
    free = search.add_argument_group("any camera (not on the hemisphere)")
    free.add_argument(
        "--free", action="store_true", help="find any camera's position, orientation and lens"
    )
    free.add_argument("--fov", type=float, metavar="DEG", help="the photo's horizontal fov")
    free.add_argument(
        "--intrinsics", metavar="FX,FY,CX,CY", help="the photo's OpenCV intrinsics in its pixels"
    )
    free.add_argument(
        "--distortion", metavar="K1,K2,P1,P2[,K3]", help="the photo's lens distortion"
    )
    free.add_argument(
        "--attitude",
        metavar="PITCH,ROLL",
        help="the camera's pitch (90: straight down) and roll in degrees, from a flight log",
    )
    free.add_argument(
        "--no-exif",
        action="store_true",
        help="do not read the photo's metadata (a drone's calibration and gimbal angles in its "
        "XMP, the EXIF focal length): estimate the focal length from the boxes",
    )
    search.add_argument(
        "--retry-for",
        type=float,
        default=DEFAULT_RETRY_BUDGET_S,
        metavar="SECONDS",
        help="wait out a controller that answers 429 or 503 with Retry-After for up to this "
        "many seconds in all (0: give up at once)",
    )
    search.set_defaults(run=run)
