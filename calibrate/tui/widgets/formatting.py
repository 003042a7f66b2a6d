"""Short text formats shared by the panels."""

from __future__ import annotations

import math

from rich.text import Text


def duration(seconds: float | None) -> str:
    """``m:ss`` (or ``h:mm:ss``) for a duration in s; ``--:--`` when unknown."""
    if seconds is None or not math.isfinite(seconds):
        return "--:--"
    total = max(0, int(round(seconds)))
    hours, rest = divmod(total, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def number(value: object) -> str:
    """A check value or threshold as short text: 4 significant digits for floats, as-is otherwise."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def text_bar(fraction: float, width: int, style: str, empty_style: str = "grey23") -> Text:
    """A progress bar of ``width`` cells: filled ``━`` in ``style``, the rest in ``empty_style``;
    a half cell ``╸`` shows the remainder."""
    fraction = min(max(float(fraction), 0.0), 1.0)
    halves = int(round(fraction * width * 2))
    full, half = divmod(halves, 2)
    bar = Text("━" * full, style=style)
    if half:
        bar.append("╸", style=style)
    bar.append("━" * (width - full - half), style=empty_style)
    return bar
