"""One-line banner across the top for hints, faults, stop requests and run outcomes."""

from __future__ import annotations

from rich.text import Text
from textual.widgets import Static

LEVELS = ("fault", "warning", "info", "hint")


class Banner(Static):
    """Hidden until the first ``show``; the level picks the colours (CSS classes ``-fault/-warning/-info/-hint``)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("", **kwargs)
        self.level: str | None = None
        self.display = False

    def show(self, text: str, level: str) -> None:
        if level not in LEVELS:
            raise ValueError(f"banner level must be one of {LEVELS}, not {level!r}")
        for name in LEVELS:
            self.set_class(name == level, f"-{name}")
        self.level = level
        self.update(Text(text))  # plain text: a path or message with [brackets] is no markup
        self.display = True
