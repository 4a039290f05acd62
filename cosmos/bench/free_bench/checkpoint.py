"""A long ``cosmos bench --free`` run in chunks: every finished search is appended to a JSON-lines
checkpoint, and the same command run again skips what it holds.

The first line is the run's fingerprint (what decides its targets and searches: seed, counts,
scenes, variants, render settings); a checkpoint of another fingerprint is set aside (renamed
``.old``) rather than mixed in. A line cut off by a killed run is dropped. The run removes the
checkpoint once its report is complete.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cosmos.bench.free_bench.records import FreeRecord

__all__ = ["Checkpoint", "Key", "key_of"]

Key = tuple[str, str, int, bool]
"""(scene, variant, target index, searched with an onboarded model)."""


def key_of(record: FreeRecord) -> Key:
    return (record.scene, record.variant, record.index, record.onboarded)


class Checkpoint:
    """The records a run with ``fingerprint`` finished so far, kept in ``path``."""

    def __init__(self, path: Path, fingerprint: Mapping[str, Any]) -> None:
        self.path = path
        self.fingerprint = json.loads(json.dumps(fingerprint))
        self.records: dict[Key, FreeRecord] = {}
        self.set_aside = False
        if path.exists():
            self._load()
        if not self.records:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"fingerprint": self.fingerprint}) + "\n")

    def _load(self) -> None:
        lines = self.path.read_text().splitlines()
        head: Any = None
        try:
            head = json.loads(lines[0]) if lines else None
        except json.JSONDecodeError:
            pass
        if not isinstance(head, dict) or head.get("fingerprint") != self.fingerprint:
            self.path.replace(self.path.with_name(self.path.name + ".old"))
            self.set_aside = True
            return
        for line in lines[1:]:
            try:
                record = FreeRecord.model_validate_json(line)
            except ValidationError:
                continue  # cut off by a killed run: searched again
            self.records[key_of(record)] = record

    def add(self, record: FreeRecord) -> None:
        """Keep ``record`` (on disk at once)."""
        self.records[key_of(record)] = record
        with self.path.open("a") as file:
            file.write(record.model_dump_json() + "\n")

    def remove(self) -> None:
        """The run is complete: no checkpoint to resume from."""
        self.path.unlink(missing_ok=True)
