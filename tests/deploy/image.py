"""The Dockerfile as BuildKit reads it (the ``dockerfile`` package wraps BuildKit's parser):
its instructions, environment, user, and what it copies before ``pip install .``."""

from __future__ import annotations

import re
from functools import cache

import dockerfile

from tests.support import ROOT

__all__ = ["WORKDIR", "copied_before_install", "dockerfile_user_id", "env", "instructions", "of"]

WORKDIR = "/app"


@cache
def instructions() -> tuple[dockerfile.Command, ...]:
    return dockerfile.parse_file(str(ROOT / "Dockerfile"))


def of(cmd: str) -> list[dockerfile.Command]:
    return [instruction for instruction in instructions() if instruction.cmd.upper() == cmd]


def dockerfile_user_id() -> int:
    """The user id the image runs as (``useradd --uid``), which Kubernetes' runAsUser names."""
    [user] = of("USER")
    [useradd] = [run for run in of("RUN") if "useradd" in run.value[0]]
    match = re.search(rf"useradd\b.*--uid (\d+).* {user.value[0]}\b", useradd.value[0])
    assert match, "the image's user has no fixed id"
    return int(match.group(1))


def env() -> dict[str, str]:
    pairs = [run.value for run in of("ENV")]
    return {k: v for values in pairs for k, v in zip(values[::2], values[1::2], strict=True)}


def copied_before_install() -> list[str]:
    """What the image copies into its working directory before ``pip install .``."""
    copied = []
    for instruction in instructions():
        installs = re.search(r"\bpip install\b.* \.$", instruction.value[0])
        if instruction.cmd.upper() == "RUN" and installs:
            return copied
        if instruction.cmd.upper() == "COPY":
            copied += instruction.value[:-1]
    raise AssertionError("the Dockerfile never runs pip install .")
