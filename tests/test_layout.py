"""The tree's shape: no module outside ``tests/`` grows past 500 lines unless its docstring says
why (a module's size is a smell that it has taken on a second job)."""

from __future__ import annotations

import ast
import subprocess

from tests.support import ROOT

MAX_LINES = 500
REASON = "over 500 lines because"
"""What a longer module's docstring must say, followed by its reason."""


def _modules() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    return [path for path in listed if not path.startswith("tests/")]


def test_the_tree_lists_its_modules():
    assert "services/controller/api.py" in _modules()


def test_no_module_outside_tests_is_over_500_lines_without_a_reason():
    too_long = []
    for path in _modules():
        text = (ROOT / path).read_text(encoding="utf-8")
        if text.count("\n") <= MAX_LINES:
            continue
        docstring = ast.get_docstring(ast.parse(text)) or ""
        if REASON not in " ".join(docstring.split()):
            too_long.append(f"{path} ({text.count(chr(10))} lines)")
    assert not too_long, (
        f"over {MAX_LINES} lines, with no '{REASON} …' in the docstring: {', '.join(too_long)}"
    )
