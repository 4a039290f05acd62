"""The settings table, ``docs/SETTINGS.md``: written from the settings classes, current, and
listing every variable with the services that read it."""

from __future__ import annotations

import re
from pathlib import Path

from cosmos.environment import READERS
from tools.export_settings import SETTINGS_PATH, main, render_settings

ROOT = Path(__file__).resolve().parents[2]


def settings_table() -> dict[str, tuple[str, ...]]:
    """Each ``COSMOS_`` variable of ``docs/SETTINGS.md`` and its "read by" column."""
    table: dict[str, tuple[str, ...]] = {}
    for row in SETTINGS_PATH.read_text().splitlines():
        if not row.startswith("| `COSMOS_"):
            continue
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        [name] = re.findall(r"`([A-Z_]+)`", cells[0])
        assert name not in table, f"{name} is in the table twice"
        table[name] = tuple(part.strip(" `") for part in cells[1].split(","))
    return table


def test_the_committed_table_is_current(capsys):
    assert SETTINGS_PATH == ROOT / "docs" / "SETTINGS.md"
    assert SETTINGS_PATH.read_text() == render_settings(), (
        "docs/SETTINGS.md is stale: run python -m tools.export_settings"
    )
    assert main(["--check"]) == 0
    assert "up to date" in capsys.readouterr().out


def test_the_table_lists_every_variable_and_who_reads_it():
    assert settings_table() == dict(READERS)


def test_every_variable_says_what_it_means():
    for row in SETTINGS_PATH.read_text().splitlines():
        if row.startswith("| `"):
            meaning = row.strip("|").split("|")[-1].strip()
            assert len(meaning) > 10, row
