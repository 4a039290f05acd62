"""``cosmos scenes add PATH`` (or ``cosmos onboard PATH``): train, measure and install the scene's
own detector beside its file, with a progress bar. The work itself is :mod:`training.onboard`
(imported when the command runs: it needs the ``train`` extra)."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

from cosmos.cli.common import Commands
from services.renderer.settings import RendererSettings

__all__ = ["ONBOARD_HELP", "add_arguments", "register", "run"]

ONBOARD_HELP = "train, measure and install a scene's own detector beside its file"


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


def run(args: argparse.Namespace) -> int:
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the scene file (YAML); its assets lie in its folder")
    parser.add_argument("--work", help="folder for renders and checkpoints (data/onboard/<id>)")
    parser.add_argument("--images", type=int, help="training images to render")
    parser.add_argument("--val-images", type=int, help="held-out images to render")
    parser.add_argument("--epochs", type=int, help="fine-tuning epochs")
    parser.add_argument("--max-minutes", type=float, help="wall-time budget of the whole run")
    parser.add_argument("--seed", type=int, help="seed of the renders (held-out: seed + 1000)")
    parser.add_argument("--tiny", action="store_true", help="a CI-sized run (plumbing only)")
    parser.set_defaults(run=run)


def register(commands: Commands) -> None:
    """Add ``cosmos onboard`` (``cosmos scenes add``'s other name) to ``commands``."""
    add_arguments(commands.add_parser("onboard", help=ONBOARD_HELP + " (= scenes add)"))
