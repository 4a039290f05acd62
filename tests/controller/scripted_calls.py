"""The call counting and scripted faults that the controller tests' fake stages share."""

from __future__ import annotations

from collections import Counter


class ScriptedCalls:
    """Counts every stage call by name (``calls``); a call named in ``faults`` answers ``n``
    times, then raises the error scripted for it."""

    def __init__(self, faults: dict[str, tuple[int, BaseException]] | None = None) -> None:
        self.faults = faults or {}
        self.calls: Counter[str] = Counter()

    def _call(self, name: str) -> None:
        self.calls[name] += 1
        if name in self.faults:
            answers, error = self.faults[name]
            if self.calls[name] > answers:
                raise error
