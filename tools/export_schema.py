"""Write the scene format's JSON Schema to ``docs/scene.schema.json``, or check that it is current.

Run ``python -m tools.export_schema [--check] [--out PATH]``. The file is
:func:`services.common.geometry.scene.scene_json_schema` as JSON with two-space indents, sorted
keys and a
trailing newline, so regenerating it gives the same bytes and a diff shows only real changes.
``--check`` writes nothing and exits with status 1 when the file is missing or out of date (for CI).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from services.common.geometry.scene import scene_json_schema

__all__ = ["SCHEMA_PATH", "main", "render_schema"]

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "docs" / "scene.schema.json"
"""Where the committed schema lives."""


def render_schema() -> str:
    """The scene JSON Schema as the exact text committed in ``docs/``."""
    return json.dumps(scene_json_schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the schema file; return the process exit status."""
    parser = argparse.ArgumentParser(prog="python -m tools.export_schema", description=__doc__)
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if the file is missing or differs from the current schema",
    )
    parser.add_argument("--out", type=Path, default=SCHEMA_PATH, help="schema file to write")
    args = parser.parse_args(argv)
    out: Path = args.out
    expected = render_schema()
    if args.check:
        try:
            current = out.read_text(encoding="utf-8")
        except FileNotFoundError:
            current = None
        if current != expected:
            print(
                f"{out} is out of date; regenerate it with python -m tools.export_schema",
                file=sys.stderr,
            )
            return 1
        print(f"{out} is up to date")
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(expected, encoding="utf-8", newline="\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
