"""``cosmos bench``'s list options: repeated, they add up; given once, they replace the default."""

from __future__ import annotations

import pytest

from cosmos.cli import _parser


@pytest.mark.parametrize(
    ("argv", "scenes", "variants"),
    [
        ([], "demo,garden", None),
        (["--scene", "garden"], "garden", None),
        (["--scene", "demo", "--scene", "garden"], "demo,garden", None),
        (["--scenes", "demo,garden", "--scene", "rand"], "demo,garden,rand", None),
        (["--variants", "clean", "--variants", "jpeg,noise"], "demo,garden", "clean,jpeg,noise"),
    ],
)
def test_repeated_list_options_add_up(argv: list[str], scenes: str, variants: str | None) -> None:
    args = _parser().parse_args(["bench", *argv])
    assert args.scenes == scenes
    assert args.variants == variants
    assert args.starts == "given,predicted"
